"""A test module's own ROS domain and rclpy context (localhost only)."""
from __future__ import annotations

import os


def domain_id_for(module_index: int) -> int:
    """A test module's own ROS_DOMAIN_ID: ``BEVO_TEST_DOMAIN_BASE`` (default 60) + its index, so
    two checkouts testing side by side on one host keep their DDS traffic apart."""
    return int(os.environ.get("BEVO_TEST_DOMAIN_BASE", "60")) + module_index


def ros_context(domain_id: int):
    """Body of a module's ``context`` fixture (``yield from ros_context(DOMAIN_ID)``): an rclpy
    context on the module's own domain, localhost only; torch's thread count restored afterwards
    (a node sets torch_threads process-wide)."""
    import rclpy
    import torch

    threads = torch.get_num_threads()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.shutdown(context=ctx)
    torch.set_num_threads(threads)
