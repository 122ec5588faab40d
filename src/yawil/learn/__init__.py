"""Training: a dataset in, a checkpoint out (docs/training.md). Read in the order a step runs:

- `config`: `TrainConfig`, every setting of a run with the paper's values as defaults
- `sampling`: which samples each step sees (epoch order, weighted draws) and the `Batch` they become
- `augment`: image augmentation on the device, drawn from the step's own generator
- `loss`: the action, speed and auxiliary losses
- `validate`: the held-out split's loss and errors (the columns of metrics.csv)
- `state`: where a run is and the random states, for an exact resume
- `stop`: Ctrl-C / SIGTERM ends a run after the current step
- `setup`: what a run starts from: the splits and their loaders, the network, the resume check
- `loop`: `train(cfg)`, the loop that ties these together and writes the run folder
- `artifacts`: metrics.csv, loss.png, best.pt as a link
- `distributed`: the same loop under torchrun (DDP)
- `export`: a checkpoint to ONNX (`yawil export`)
- `cli`: `yawil train`

The checkpoint format itself is `yawil.policy.checkpoint` (the agent reads it without this package).
Nothing is imported here, so that `yawil --help` stays fast; import the submodules.
"""
