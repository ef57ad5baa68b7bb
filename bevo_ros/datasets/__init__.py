"""Recordings: rosbag2 -> tensors and the engine's feeding order (``rosbag``), KITTI readers (``kitti``)
and KITTI -> rosbag2 (``kitti_bag``), synthetic drives and aerial maps with exact ground truth (``synthetic``)."""
