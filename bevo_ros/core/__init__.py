"""The BEVO engine: pure PyTorch, no ROS imports. Batched tensors, shapes in docstrings."""
