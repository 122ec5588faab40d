"""Explanation: where a trained network looked (docs/explain.md, the paper's Figures 8 and 9).

- `attention`: the maps of an agent on a frame, a stored record or an observation; `explain_frames` (figures
  of dataset frames and a grid) and `explain_episode` (a driven episode as a video)
- `figures`: a map upsampled, coloured and blended over the image; one frame's figure, a grid
- `faithfulness`: whether the outputs depend on what the maps point at: the deletion test, open and closed loop
  (docs/explain.md)
- `by_class`: each map's mass per semantic class against the class's pixel share, by situation (docs/explain.md)
- `cli`: `yawil explain`

Nothing is imported here, so that `yawil --help` stays fast; import the submodules.
"""
