"""The linear unit of a coordinate reference system (WKT), so sizes given in metres fit data in feet.

LAS/LAZ files carry their CRS as WKT (or GeoTIFF keys, which the reader turns into WKT when pyproj is there).
A projected CRS names the unit of its easting and northing: ``UNIT["foot",0.3048]`` (WKT1) or
``LENGTHUNIT["US survey foot",0.304800609601219]`` (WKT2); a geographic CRS is in degrees. Parsed here without
pyproj, which is optional.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .errors import InputError

__all__ = ["LinearUnit", "linear_unit", "METRE", "parse_length", "LENGTH_UNITS", "check_same_crs", "crs_name"]


@dataclass(frozen=True)
class LinearUnit:
    """A unit of length: its name and how many metres it is (``None``: angular, i.e. a geographic CRS)."""

    name: str
    metres: float | None


METRE = LinearUnit("metre", 1.0)

#: Units a length may be written in (``"0.1 m"``, ``"0.33 ft"``), in metres.
LENGTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048, "us-ft": 1200.0 / 3937.0}

_TOKEN = re.compile(r'\s*(?:"((?:[^"]|"")*)"|([\[\](),])|([^\[\](),"]+))')


def _parse(wkt: str) -> list:
    """WKT as nested lists ``[keyword, child, ...]`` (strings and numbers as text); a small recursive reader."""
    pos = 0
    stack: list[list] = [["<root>"]]
    last: list | None = None
    while pos < len(wkt):
        m = _TOKEN.match(wkt, pos)
        if m is None or m.end() == pos:
            break
        pos = m.end()
        quoted, punct, word = m.groups()
        if punct is not None and punct in "[(":
            if last is None:
                raise ValueError("bracket without a keyword")
            stack[-1].pop()  # the keyword just read becomes a node
            stack[-1].append(last)
            stack.append(last)
            last = None
        elif punct is not None and punct in "])":
            if len(stack) == 1:
                raise ValueError("unbalanced brackets")
            stack.pop()
            last = None
        elif punct == ",":
            last = None
        elif quoted is not None:
            stack[-1].append(quoted)
            last = None
        elif word is not None and word.strip():
            last = [word.strip().upper()]
            stack[-1].append(word.strip())
    return stack[0][1:]


def _children(node: list, names: tuple[str, ...]) -> list[list]:
    return [c for c in node[1:] if isinstance(c, list) and c[0] in names]


def _unit_of(node: list) -> LinearUnit | None:
    """The length unit of a projected or engineering CRS node (its own UNIT, else its axes')."""
    for holder in [node, *_children(node, ("CS", "AXIS"))]:
        for u in _children(holder, ("UNIT", "LENGTHUNIT")):
            if len(u) >= 3:
                try:
                    factor = float(u[2])
                except (TypeError, ValueError):
                    continue
                if factor > 0:
                    return LinearUnit(str(u[1]), factor)
    return None


def _cartesian(node: list) -> bool:
    """Whether a WKT2 geodetic CRS node has a Cartesian coordinate system (geocentric, not latitude/longitude)."""
    return any(len(cs) > 1 and str(cs[1]).strip().lower() == "cartesian" for cs in _children(node, ("CS",)))


def linear_unit(wkt: str | None) -> LinearUnit | None:
    """The horizontal unit of a WKT CRS: metres per unit, or ``metres=None`` for a geographic CRS.

    Returns ``None`` when there is no CRS or it cannot be read (the caller then assumes metres).
    """
    if not wkt or not isinstance(wkt, str):
        return None
    try:
        nodes = _parse(wkt)
    except (ValueError, IndexError):
        return None
    projected = ("PROJCS", "PROJCRS", "PROJECTEDCRS", "LOCAL_CS", "ENGCRS", "ENGINEERINGCRS")
    geographic = ("GEOGCS", "GEOGCRS", "GEOGRAPHICCRS", "GEODCRS", "GEODETICCRS", "GEOCCS")
    queue = list(nodes)
    while queue:
        node = queue.pop(0)
        if not isinstance(node, list):
            continue
        if node[0] in projected:
            return _unit_of(node)
        if node[0] == "GEOCCS" or (node[0] in geographic and _cartesian(node)):
            return _unit_of(node)  # geocentric (earth-centred X Y Z): a length, metres in practice
        if node[0] in geographic:
            return LinearUnit("degree", None)
        if node[0] in ("COMPD_CS", "COMPOUNDCRS", "BOUNDCRS", "SOURCECRS"):
            queue = [c for c in node[1:] if isinstance(c, list)] + queue  # the horizontal part comes first
    return None


def parse_length(value) -> tuple[float, str | None]:
    """A length as given: a number (the data's units) or ``"<number> <unit>"`` with a unit of
    :data:`LENGTH_UNITS`. Returns the number and the unit (``None``: data units).

    Raises
    ------
    ValueError
        Text that is neither.
    """
    if isinstance(value, str):
        m = re.fullmatch(r"\s*([-+0-9.eE]+|nan|inf)\s*([A-Za-z-]*)\s*", value)
        if m is None:
            raise ValueError(value)
        number, unit = float(m.group(1)), m.group(2).lower() or None
        if unit is not None and unit not in LENGTH_UNITS:
            raise ValueError(value)
        return number, unit
    return value, None


def check_same_crs(declared: list[tuple[str | None, str]]) -> None:
    """Refuse inputs in different CRSs (merging would place one survey's points in another's frame without a
    word), and inputs of which some declare a CRS and some do not (the bare ones' coordinates may be in any
    frame: nothing can be stated for them here, so they are not assumed to be in the others').

    Parameters
    ----------
    declared : list of (CRS or None, source)
        What each input (or chunk of one: ``path[start:stop]``) declares; sources name the files in messages.

    Raises
    ------
    InputError
        Naming the first two inputs that disagree and their CRSs.
    """
    named = [(c, s) for c, s in declared if c]
    for crs, source in named[1:]:
        if _crs_text(crs) != _crs_text(named[0][0]):
            raise InputError(f"inputs in different coordinate reference systems: {_file_of(named[0][1])} "
                             f"({crs_name(named[0][0])}) and {_file_of(source)} ({crs_name(crs)}); "
                             "reproject them to one first")
    bare = [s for c, s in declared if not c]
    if named and bare:
        raise InputError(f"inputs with and without a coordinate reference system: {_file_of(named[0][1])} "
                         f"({crs_name(named[0][0])}) and {_file_of(bare[0])} (none declared); if "
                         f"{_file_of(bare[0])} is in {crs_name(named[0][0])}, give it as LAS/LAZ declaring that CRS, "
                         "otherwise reproject it first")


def _crs_text(crs: str) -> str:
    """A CRS's text without the layout whitespace outside quoted names (WKT pretty-printed or not)."""
    return re.sub(r'\s+(?=(?:[^"]*"[^"]*")*[^"]*$)', "", crs)


def _file_of(source) -> str:
    """The file of a chunk's ``source`` (``path[start:stop]``), as messages show it (a URL without its query)."""
    from .io.remote import shown

    return shown(re.sub(r"\[\d+:\d+\]$", "", str(source)))


def crs_name(crs: str) -> str:
    """A short name for a CRS in a message: the WKT's first quoted name, else its start."""
    m = re.search(r'"([^"]+)"', crs)
    return m.group(1) if m else crs.split("\n")[0][:60]
