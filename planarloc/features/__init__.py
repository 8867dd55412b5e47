"""Image features: local features (RootSIFT, tilt augmentation), matching, retrieval, image reading.

:mod:`~planarloc.features.images` reads images (files, bytes, arrays) as gray arrays;
:mod:`~planarloc.features.extract` detects local features; :mod:`~planarloc.features.tilt` is the
paper's tilt augmentation of map images; :mod:`~planarloc.features.matching` matches two images;
:mod:`~planarloc.features.retrieval` is the VLAD image retrieval and hloc pairs lookup.
"""
