"""The environment every rclpy process of genreg's tools needs (no rclpy import: safe before ROS loads).

Processes that talk to register_node stay on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), share one
ROS_DOMAIN_ID and load the shipped Fast DDS profile for large clouds (config/fastdds_large_clouds.xml, read
when a process creates its first DDS participant). The replay harness, the node benchmark script and the
test fixtures all take their variables from `ros_environment`.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Mapping
from pathlib import Path

FASTDDS_PROFILE = Path(__file__).resolve().parents[1] / "config" / "fastdds_large_clouds.xml"


def random_domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..100 (valid Fast DDS ports on Linux; 0, ROS's default, left to users)."""
    return 1 + secrets.randbelow(100)


def ros_environment(domain_id: int | str | None = None, profile: str | os.PathLike | None = None,
                    environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """The discovery and transport variables for an rclpy process (returned, not applied).

    `domain_id`: the ROS_DOMAIN_ID; None keeps the one of `environ` (default: os.environ) if set, else a
    random one (`random_domain_id`). `profile`: the Fast DDS profile file; None keeps `environ`'s
    FASTDDS_DEFAULT_PROFILES_FILE if set, else the shipped one (`FASTDDS_PROFILE`)."""
    environ = os.environ if environ is None else environ
    if domain_id is None:
        domain_id = environ.get("ROS_DOMAIN_ID") or random_domain_id()
    if profile is None:
        profile = environ.get("FASTDDS_DEFAULT_PROFILES_FILE") or FASTDDS_PROFILE
    return {
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": str(domain_id),
        "FASTDDS_DEFAULT_PROFILES_FILE": str(profile),
        "RCUTILS_COLORIZED_OUTPUT": "0",
    }
