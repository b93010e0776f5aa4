"""Server perception: one keyframe's images -> object instances -> 3D object measurements.

The entry point is :func:`wardmap.server.perception.keyframe.measure_keyframe`. The modules,
in the order a keyframe passes them:

- ``keyframe.py``: the steps in their one order; decoding of keyframe messages;
- ``models.py``: the segmenters (the trained network, a YOLOX detector) and ``make_segmenter``;
- ``instances.py``: instances from a class map or the simulator's ground truth, split into
  one instance per object;
- ``floor.py``: the floor checks (floating, pieces of a taller surface, flat on the floor);
- ``measure.py``: the 3D measurement of each instance (paper 000 Eq. 1).

Beside them: ``config.py`` (``[perception]`` settings), ``types.py`` (``Instance``,
``ObjectMeasurement``), ``masks.py`` (mask geometry several steps share) and ``segment.py``
(``wardmap segment``).
"""
