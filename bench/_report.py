"""What every bench does with its report: write it as JSON, creating the folder, with what a
reader needs to repeat it (the command, the date, the host's processor and the versions)."""

import datetime
import json
import os
import platform
import shlex
import sys
from importlib import metadata


def _cpu_model():
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def _versions(names=("orthowarp", "warp-lang", "numpy", "rasterio", "pyproj", "scipy", "orthority")):
    found = {}
    for name in names:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return found


def provenance():
    """{command, date (UTC), host: {cpu, cores, python}, versions} of this run."""
    return dict(command="python3 " + shlex.join(sys.argv),
                date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                host=dict(cpu=_cpu_model(), cores=os.cpu_count(), python=platform.python_version()),
                versions=_versions())


def save_report(report, path, *, indent=1):
    """Write a benchmark report (a JSON-serialisable object) to ``path``, folders created; the
    run's :func:`provenance` is added under keys the report does not already have."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    for key, value in provenance().items():
        report.setdefault(key, value)
    with open(path, "w") as f:
        json.dump(report, f, indent=indent)
