"""Ground-truth generator: path-traced RGB-D sequences with per-frame lighting truth.

`arlight synth` renders sequences in the layout and conventions of ``../shared/data/synthetic``
(TUM folders, ``camera.json``, ``groundtruth.txt``, clean and sensor-like depth,
``lighting_gt.json``, AR pairs in ``ar/``) under any equirectangular HDR map. Only
:mod:`arlight.synth.render` imports Mitsuba 3 (the ``synth`` extra); the layouts, the
lighting truth and the file writers are plain NumPy and run without it.
"""
