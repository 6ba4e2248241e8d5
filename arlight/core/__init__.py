"""The lowest layer, which every other package depends down on (docs/architecture.md).

`checks` (the checks made where data enters), `contracts` (the frame path's typed contracts),
`camera` (the pinhole camera) and `frames` (a frame's input and result). Nothing here imports
another arlight package.
"""
