"""genreg-replay: bags of RGB-D clouds through register_node, scored against their ground truth.

- `harness`: the node process, the rclpy client that relays pairs and records outputs, `replay()`;
- `scoring`: per-pair results, reasons for missing outputs, the ICP reference, the summary figures;
- `report`: the summary table and the report folder;
- `cli`: the `genreg-replay` command (`python -m genreg_ros.replay`).
"""

from genreg_ros.replay.cli import main

__all__ = ["main"]
