"""arlight.sources: where frames come from, for the pipeline and for the capture client.

- recorded data sets (`sequence.open_sequence`: TUM RGB-D, Open3D/Redwood, 7-Scenes, single
  colour + depth pairs; one module per layout) and the depth encodings they store
  (`depth_encodings`);
- the built-in procedural scene with known light (`synthetic`);
- MCAP recordings made by `arlight record` (`recording`, the reader; the writer is the
  capture client's, `arlight.client.recording`);
- `source.Source`: any of these as the capture client streams it (`open_source`).
- virtual-scene files, the objects to render into the image (`virtual_scene_file`,
  docs/scene-files.md).

Depth leaves every source as the sensor's integers: (H, W) uint16 with `depth_scale` units
per metre (`FrameInput.depth_scale`; TUM 5000, millimetres 1000). Where the stored values are
not linear integers (NYU raw disparity, 7-Scenes depth reprojected into the colour camera) the
reader converts them into uint16 at a stated scale. Metres are computed once, by
`arlight.core.checks.depth_metres`, where the pipeline takes the frame.

Depends on `arlight.pipeline` (FrameInput, PinholeCamera, splat) and `arlight.protocols`
(recorded frames, calibration); never on the client or the server.
"""
