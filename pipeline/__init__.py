"""The job layer of tiled_gridpull: command line, Dask graph, progress and retries.

Imports point one way: ``pipeline`` uses :mod:`tiled_gridpull`, never the reverse.
"""
