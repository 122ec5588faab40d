"""What a trained network needs around it, for training and inference alike: where and how it computes
(`yawil.policy.runtime`) and the one model-input contract (`yawil.policy.inputs`).

Below `yawil.train`, `yawil.agent`, `yawil.explain` and `yawil.export` in the import graph: it imports none of
them, so inference does not depend on the training module. Nothing is imported here; import the submodules.
"""
