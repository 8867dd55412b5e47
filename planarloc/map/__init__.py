"""The map: posed images with their features, in one SQLite file (no 3D model).

:mod:`~planarloc.map.posed_image` is the record every importer produces and every map stores;
:mod:`~planarloc.map.schema` the tables and opening a file as a map; :mod:`~planarloc.map.codec`
the byte layout of rows; :mod:`~planarloc.map.store` reads and writes maps
(:class:`~planarloc.map.store.MapDatabase`); :mod:`~planarloc.map.lock` lets writers take turns;
:mod:`~planarloc.map.settings` the settings a map is built with; :mod:`~planarloc.map.identity`
tells changed images from the same ones; :mod:`~planarloc.map.gravity` stores the map's gravity;
:mod:`~planarloc.map.integrity` checks every row; :mod:`~planarloc.map.builder` builds a map.
"""
