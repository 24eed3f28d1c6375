"""Physics through the rig, below the networks: the differentiable rig layer (the phase head is built on
it) and phase refinement of predicted heights."""
