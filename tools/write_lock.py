#!/usr/bin/env python3
"""Turn a `pip install --dry-run --report` JSON into a fully pinned requirements.txt."""
import json
import sys
from pathlib import Path


def main(report_path: str, out_path: str) -> None:
    report = json.loads(Path(report_path).read_text())
    rows = sorted((i["metadata"]["name"], i["metadata"]["version"]) for i in report["install"])
    lines = ["# Fully pinned lock of requirements.in (regenerate with `make lock`)."]
    for name, version in rows:
        version = version.split("+")[0]  # torch's local tag (+cpu) comes from the on-disk wheel
        extra = "[fastrtps]" if name == "ros-jazzy-rclpy" else ""
        lines.append(f"{name}{extra}=={version}")
    tmp = Path(out_path + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(out_path)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
