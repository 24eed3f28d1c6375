"""Physics through the rig: the differentiable rig layer, phase refinement, label-free adaptation."""
