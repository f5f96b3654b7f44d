"""Procedural RGB-D indoor scenes: the training data and the sample bags.

* :mod:`.generate` - ``generate_frame(seed, SynthConfig)`` -> :class:`~shape_detector.types.Frame` with full
  ground truth; ``generate_sequence`` (one room, moving hand-held camera).
* :mod:`.layout` (rooms, walls with doors / windows / recesses, furniture groups, clutter),
  :mod:`.furniture` (part models of the ten classes + clutter items), :mod:`.camera` (intrinsics, poses),
  :mod:`.render` (cuboid z-buffer rasteriser + shader), :mod:`.textures`, :mod:`.noise` (depth sensor model).
* :mod:`.dataset` - training shards (``write_shards`` / ``iter_frames``); :mod:`.bag` - rosbag2 MCAP + ``gt.json``;
  :mod:`.figure` - README grid; :mod:`.bench` - frames/s; :mod:`.cli` - ``shape-detector synth ...``.

Submodules are imported on demand (nothing heavy is loaded by ``import shape_detector.synth``).
"""
