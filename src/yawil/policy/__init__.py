"""A trained policy and what it needs around it, for training and inference alike: the checkpoint format,
normalisation statistics and model rebuild (`yawil.policy.checkpoint`), where and how it computes
(`yawil.policy.runtime`) and the one model-input contract (`yawil.policy.inputs`).

Below `yawil.learn`, `yawil.agent` and `yawil.explain` in the import graph: it imports none of them, so
inference does not depend on the training package. Nothing is imported here; import the submodules.
"""
