"""What every bench does with its report: write it as JSON, creating the folder."""

import json
import os


def save_report(report, path, *, indent=1):
    """Write a benchmark report (a JSON-serialisable object) to ``path``, folders created."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(report, f, indent=indent)
