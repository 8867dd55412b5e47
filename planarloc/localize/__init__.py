"""Localization: one query (:mod:`~planarloc.localize.localizer`) or a stream of frames
(:mod:`~planarloc.localize.sequence`) against a map.

Every front door (CLI, service, ROS node) prepares its input with
:meth:`planarloc.localize.localizer.Localizer.prepare` into a :class:`~planarloc.localize.query.Query`
(the image, the camera, defaulting to the map's, the gravity and the references, checked once),
configures with :func:`~planarloc.localize.localizer.localizer_config`, and writes the records of
:mod:`~planarloc.localize.records`.
"""
