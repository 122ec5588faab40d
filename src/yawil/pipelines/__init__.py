"""Pipelines: the stages of the loop run one after another, each resumable (skipped when finished,
by the markers of `yawil.stages`, which the square experiment of `yawil.bench.experiments` uses too).

- `demo`: `yawil demo` / `make demo`, the whole loop at a small scale
- `reproduce`: `yawil reproduce`, every experiment of the paper
- `dagger`: `yawil dagger`, on-policy rounds (the learner drives, the expert labels and takes over; collect,
  train and benchmark in turn)

Nothing is imported here, so that `yawil --help` stays fast; import the submodules.
"""
