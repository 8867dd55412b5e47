"""Gravity: where down is, in a world and in a camera.

:mod:`~planarloc.gravity.world`: a world's down direction (declared by a format, given as ``up=``,
or estimated from a map's camera poses) and the report ``planarloc map info`` prints;
:mod:`~planarloc.gravity.upright`: a camera's mount pitch/roll and the rotation that makes it upright.
"""
