"""orthowarp._driver: which device a command line asks for, and a driver start that changes
nothing where there is no CUDA driver (this machine) and imports no Warp."""

import subprocess
import sys

import pytest

from orthowarp._driver import device_ordinal


@pytest.mark.parametrize("argv, expected", [
    (["ortho", "a.tif"], 0),                        # the default device: the first GPU where there is one
    (["ortho", "--device", "cuda"], 0),
    (["ortho", "-d", "cuda:3", "a.tif"], 3),
    (["mosaic", "--device=cuda:1"], 1),
    (["ortho", "--device", "cpu"], None),
    (["ortho", "-d", "cuda:x"], None),              # not a device this can start: left to the job's own message
    (["ortho", "--device"], 0),                     # no value: click reports it; nothing to start here
])
def test_device_ordinal(argv, expected):
    assert device_ordinal(argv) == expected


def test_a_driver_start_without_a_driver_ends_quietly_and_imports_no_warp():
    code = ("import sys\nfrom orthowarp._driver import start_driver\nstart_driver(0).join(30)\n"
            "print('warp' in sys.modules)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "False" and p.stderr == ""
