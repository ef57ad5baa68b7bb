"""Files and messages: rosbag2 (``bag``), ROS messages <-> numpy (``ros_conversions``), atomic files
(``files``), the learned-parameters YAML (``learned_params``), BEVO+ map files (``maps``)."""
