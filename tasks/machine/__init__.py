"""The five-axis machine as data: description, error model, effects, kinematics (forward, inverse), formulations."""
