"""crs: the horizontal unit of a WKT CRS, and lengths written with a unit."""

import pytest

from tiled_gridpull.crs import linear_unit, parse_length

GEOG = ('GEOGCS["NAD83(HARN)",DATUM["D_North_American_1983_HARN",SPHEROID["GRS_1980",6378137,298.257222101]],'
        'PRIMEM["Greenwich",0],UNIT["Degree",0.017453292519943295]]')
#: as in the shared Autzen file: a projected CRS in international feet, after a GEOGCS in degrees
FEET_WKT1 = (f'PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic",{GEOG},PROJECTION["Lambert_Conformal_Conic_2SP"],'
             'PARAMETER["false_easting",1312335.958005249],UNIT["foot",0.3048,AUTHORITY["EPSG","9002"]]]')
US_FEET_WKT2 = ('PROJCRS["NAD83 / Oregon North (ftUS)",BASEGEOGCRS["NAD83",DATUM["North American Datum 1983",'
                'ELLIPSOID["GRS 1980",6378137,298.257222101,LENGTHUNIT["metre",1]]],'
                'PRIMEM["Greenwich",0,ANGLEUNIT["degree",0.0174532925199433]]],'
                'CONVERSION["SPCS83 Oregon North zone (US Survey feet)",METHOD["Lambert Conic Conformal (2SP)"],'
                'PARAMETER["False easting",8202083.333,LENGTHUNIT["US survey foot",0.304800609601219]]],'
                'CS[Cartesian,2],AXIS["easting (X)",east,ORDER[1],LENGTHUNIT["US survey foot",0.304800609601219]],'
                'AXIS["northing (Y)",north,ORDER[2],LENGTHUNIT["US survey foot",0.304800609601219]]]')
UTM_WITH_FEET_HEIGHTS = ('COMPD_CS["UTM 31N + height in feet",PROJCS["WGS 84 / UTM zone 31N",GEOGCS["WGS 84",'
                         'UNIT["degree",0.0174532925199433]],UNIT["metre",1]],'
                         'VERT_CS["height",VERT_DATUM["x",2005],UNIT["foot",0.3048]]]')
GEOCENTRIC_WKT1 = ('GEOCCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],'
                   'UNIT["metre",1],AXIS["Geocentric X",OTHER],AXIS["Geocentric Y",OTHER],AXIS["Geocentric Z",NORTH]]')
GEOCENTRIC_WKT2 = ('GEODCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563,'
                   'LENGTHUNIT["metre",1]]],PRIMEM["Greenwich",0,ANGLEUNIT["degree",0.0174532925199433]],'
                   'CS[Cartesian,3],AXIS["(X)",geocentricX,ORDER[1],LENGTHUNIT["metre",1]],'
                   'AXIS["(Y)",geocentricY,ORDER[2],LENGTHUNIT["metre",1]],'
                   'AXIS["(Z)",geocentricZ,ORDER[3],LENGTHUNIT["metre",1]]]')
GEOG_WKT2 = ('GEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563,'
             'LENGTHUNIT["metre",1]]],PRIMEM["Greenwich",0,ANGLEUNIT["degree",0.0174532925199433]],'
             'CS[ellipsoidal,2],AXIS["latitude",north,ORDER[1],ANGLEUNIT["degree",0.0174532925199433]]]')


@pytest.mark.parametrize("wkt,name,metres", [
    (GEOCENTRIC_WKT1, "metre", 1.0),  # earth-centred X Y Z: metres, not degrees
    (GEOCENTRIC_WKT2, "metre", 1.0),
    (GEOG_WKT2, "degree", None),
    (FEET_WKT1, "foot", 0.3048),
    (US_FEET_WKT2, "US survey foot", 0.304800609601219),
    (UTM_WITH_FEET_HEIGHTS, "metre", 1.0),  # the horizontal part decides, not the last UNIT in the text
    (GEOG, "degree", None),
])
def test_horizontal_unit_of_a_crs(wkt, name, metres):
    unit = linear_unit(wkt)
    assert unit is not None and unit.name == name
    assert unit.metres == (pytest.approx(metres) if metres else None)


@pytest.mark.parametrize("wkt", [None, "", "not a crs", 'PROJCS["x",UNIT["foot"', "]]]", 'PROJCS["x"]',
                                 'PROJCS["x",UNIT["foot",-1]]'])
def test_no_or_unreadable_crs_gives_none(wkt):
    assert linear_unit(wkt) is None


@pytest.mark.parametrize("text,expected", [
    (0.3, (0.3, None)), ("0.5", (0.5, None)), ("0.1 m", (0.1, "m")), ("2ft", (2.0, "ft")),
    ("10 cm", (10.0, "cm")), (" 0.7 US-FT ", (0.7, "us-ft")),
])
def test_lengths_with_and_without_units(text, expected):
    assert parse_length(text) == expected


@pytest.mark.parametrize("text", ["0.1 furlong", "m", "0.1 m m", "ten"])
def test_bad_lengths_are_refused(text):
    with pytest.raises(ValueError):
        parse_length(text)
