"""Build hook: compile orthowarp's Warp kernels into the package (see orthowarp/_kernelcache.py).

Everything else about the package is in pyproject.toml. The kernels are compiled for the
building machine's CPU and GPUs (and the CUDA architectures in ORTHOWARP_CUDA_ARCHS), so that
a first call loads them instead of compiling; ORTHOWARP_BUILD_KERNELS=0 skips this, and a
build where it fails still installs (the kernels are then compiled on first use, as Warp
does). Editable installs skip it.
"""

import os
import subprocess
import sys

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithKernels(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("ORTHOWARP_BUILD_KERNELS", "1") == "0":
            return
        package = os.path.join(os.path.abspath(self.build_lib), "orthowarp")
        script = os.path.join(package, "_kernelcache.py")
        out = os.path.join(package, "_kernels")
        # run_path: the script's folder is not put on sys.path (its modules would shadow others)
        code = ("import runpy, sys; sys.argv = sys.argv[1:]; "
                "runpy.run_path(sys.argv[0], run_name='__main__')")
        try:
            subprocess.run([sys.executable, "-c", code, script, out, "--package", package], check=True)
        except (OSError, subprocess.CalledProcessError) as e:
            print(f"orthowarp: kernels not compiled at build ({e}); they are compiled on first use", file=sys.stderr)


setup(cmdclass={"build_py": BuildWithKernels})
