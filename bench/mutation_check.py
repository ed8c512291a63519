"""Mutation spot-check of orthowarp's core formulas (not a test): do the fast tests fail when a
formula is broken?

Each mutation is an exact text substitution in one source file. The package is copied to a
temporary folder laid out as the installed package tree (pyproject.toml's package-dir:
orthowarp/ -> orthowarp, kernels/ -> orthowarp.kernels, pipeline/ -> orthowarp.pipeline,
adjust/ -> orthowarp.adjust), with tests/ and pyproject.toml beside it; the mutation is applied
to the copy only (the checkout is never written), its chosen test node ids run in a subprocess
whose working folder is the copy (so the copy, not the editable install, is imported: checked by
``orthowarp.__file__`` in that same interpreter before pytest starts), and the copy's file is
restored afterwards (the whole copy is deleted at the end, Ctrl-C included).

A mutation is *killed* when its tests fail (pytest exit status 1), *survived* when they pass
(0); anything else (no tests collected, a usage or internal error, a timeout) is an *error*.
The tests of every mutation first run on the unmutated copy (the baseline): they must pass
there, or a "kill" would mean nothing. The original text must occur exactly once in its file,
so that a refactor makes this script fail loudly instead of silently testing nothing.

Warp compiles a kernel module per content hash: a kernel mutation compiles its module (a minute
or more on 2 cores; cached afterwards), so kernel mutations are few and run few tests.

usage: python3 bench/mutation_check.py [--out FILE.json] [--only NAME ...] [--list]
Exit status 1 when a mutation survives or errs, or the baseline fails.
"""

import argparse
import datetime
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# source folder in the checkout -> folder in the package tree of the copy
PACKAGE_DIRS = {"orthowarp": "orthowarp", "kernels": "orthowarp/kernels", "pipeline": "orthowarp/pipeline",
                "adjust": "orthowarp/adjust"}
TIMEOUT_S = 1800

T_BUNDLE = "tests/test_bundle.py::"
T_FORMATS = "tests/test_formats.py::"

# name, file (checkout path), original, replacement, what it breaks, test node ids
MUTATIONS = [
    dict(name="brown_p1_sign", file="orthowarp/brown.py",
         original="uvd = np.stack([u * rad + 2 * p1 * u * v + p2",
         replacement="uvd = np.stack([u * rad - 2 * p1 * u * v + p2",
         what="host Brown-Conrady distortion: the sign of p1's term in x (FrameCamera.distort, the bundle's "
              "collinearity)",
         tests=["tests/test_camera.py::test_host_undistort_matches_kernel[cpu-drone]", "tests/test_collinearity.py"]),
    dict(name="brown_p1_sign_kernel", file="kernels/camera.py",
         original="        u * radial + two * cam.p1 * u * v + cam.p2 * (r2 + two * u * u),",
         replacement="        u * radial - two * cam.p1 * u * v + cam.p2 * (r2 + two * u * u),",
         what="device Brown-Conrady distortion (camera_to_pixel): the sign of p1's term in x",
         tests=["tests/test_camera.py::test_camera_to_pixel_kernel_vs_reference[cpu-drone]"]),
    dict(name="kappa_rotation_sign", file="orthowarp/geodesy.py",
         original="sk, ck = np.sin(a[:, 2]), np.cos(a[:, 2])",
         replacement="sk, ck = -np.sin(a[:, 2]), np.cos(a[:, 2])",
         what="R = Rx(omega) Ry(phi) Rz(kappa) built with -kappa (Pose.from_opk, the bundle's collinearity)",
         tests=["tests/test_collinearity.py", T_FORMATS + "test_fuzz_exterior_csv_round_trip"]),
    dict(name="bilinear_weights_transposed_host", file="pipeline/dem.py",
         original="h = ((1 - ay) * ((1 - ax) * z00 + ax * z01) + ay * ((1 - ax) * z10 + ax * z11))",
         replacement="h = ((1 - ax) * ((1 - ay) * z00 + ay * z01) + ax * ((1 - ay) * z10 + ay * z11))",
         what="Dem.sample's bilinear weights with the axes exchanged",
         tests=["tests/test_dem.py::test_bilinear_sampling_between_cell_centres"]),
    dict(name="bilinear_weights_transposed_kernel", file="kernels/ortho.py",
         original=("        w01 = tap_weight(src, y0, x1, rows, cols, fx * (one - fy))\n"
                   "        w10 = tap_weight(src, y1, x0, rows, cols, (one - fx) * fy)\n"),
         replacement=("        w01 = tap_weight(src, y0, x1, rows, cols, (one - fx) * fy)\n"
                      "        w10 = tap_weight(src, y1, x0, rows, cols, fx * (one - fy))\n"),
         what="the orthorectification kernel's bilinear source weights with the axes exchanged",
         tests=["tests/test_ortho.py::test_bilinear_ortho_is_the_bilinear_source"]),
    dict(name="dem_offset_sign_host", file="pipeline/dem.py",
         original="gx = (x - t.c) / t.a - 0.5",
         replacement="gx = (x - t.c) / t.a + 0.5",
         what="Dem.sample: cell centres taken half a cell off in x",
         tests=["tests/test_dem.py::test_bilinear_sampling_between_cell_centres"]),
    dict(name="dem_offset_sign_kernel", file="kernels/dem.py",
         original="return wp.vec2d((x - dem.x0) * dem.inv_dx - half, (y - dem.y0) * dem.inv_dy - half)",
         replacement="return wp.vec2d((x - dem.x0) * dem.inv_dx + half, (y - dem.y0) * dem.inv_dy + half)",
         what="the kernels' DEM sampling: cell centres taken half a cell off",
         tests=["tests/test_ortho.py::test_bilinear_ortho_is_the_bilinear_source"]),
    dict(name="sigma0_redundancy_plus_1", file="adjust/bundle/statistics.py",
         original="s0 = float(np.sqrt(cost / redundancy))",
         replacement="s0 = float(np.sqrt(cost / (redundancy + 1)))",
         what="the bundle adjustment's sigma0 = sqrt(v'Pv / (r + 1))",
         tests=[T_BUNDLE + "test_sigma0_is_sqrt_vtpv_over_the_redundancy"]),
    dict(name="sigma0_without_sqrt", file="adjust/bundle/statistics.py",
         original="s0 = float(np.sqrt(cost / redundancy))",
         replacement="s0 = float(cost / redundancy)",
         what="the bundle adjustment's sigma0 = v'Pv / r (no square root)",
         tests=[T_BUNDLE + "test_sigma0_is_sqrt_vtpv_over_the_redundancy"]),
    dict(name="covariance_scaled_by_sigma0", file="adjust/bundle/result.py",
         original='s2 = st["sigma0"] ** 2',
         replacement='s2 = st["sigma0"]',
         what="the bundle adjustment's covariances sigma0 Q instead of sigma0^2 Q",
         tests=[T_BUNDLE + "test_covariances_are_sigma0_squared_times_the_inverse_normal_matrix",
                T_BUNDLE + "test_doubling_the_a_priori_sigmas_halves_sigma0_and_keeps_the_covariances"]),
    dict(name="csv_omega_phi_swapped", file="pipeline/formats/exterior.py",
         original="pose = Pose.from_opk(*pos, *ang, crs=map_crs)",
         replacement="pose = Pose.from_opk(*pos, ang[1], ang[0], ang[2], crs=map_crs)",
         what="the exterior-orientation CSV reader passes phi as omega and omega as phi",
         tests=[T_FORMATS + "test_fuzz_exterior_csv_round_trip"]),
]


def make_copy(dest):
    """The package tree, tests/ and pyproject.toml of the checkout under ``dest``."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for src, dst in PACKAGE_DIRS.items():
        shutil.copytree(os.path.join(ROOT, src), os.path.join(dest, dst), ignore=ignore, dirs_exist_ok=True)
    shutil.copytree(os.path.join(ROOT, "tests"), os.path.join(dest, "tests"), ignore=ignore)
    shutil.copy2(os.path.join(ROOT, "pyproject.toml"), os.path.join(dest, "pyproject.toml"))


def copy_path(dest, checkout_path):
    top, rest = checkout_path.split("/", 1)
    return os.path.join(dest, PACKAGE_DIRS[top], rest)


def check_mutations(dest):
    """Each original text occurs exactly once in its file (of the copy, identical to the checkout)."""
    for m in MUTATIONS:
        with open(copy_path(dest, m["file"])) as f:
            n = f.read().count(m["original"])
        if n != 1:
            raise SystemExit(f"mutation {m['name']}: its original text occurs {n} times in {m['file']} "
                             f"(expected once): update the mutation to the code\n  {m['original']!r}")


RUNNER = """
import os, sys
import orthowarp
where = os.path.realpath(orthowarp.__file__)
print("orthowarp imported from", where, flush=True)
if not where.startswith(os.path.realpath(sys.argv[1]) + os.sep):
    sys.exit(f"the copy was not imported: orthowarp is {where}")
import pytest
sys.exit(pytest.main(["-q", "-x", "-p", "no:cacheprovider", "-W", "ignore::DeprecationWarning", *sys.argv[2:]]))
"""


def run_tests(dest, tests, timeout):
    env = dict(os.environ, PYTHONPATH=dest + (os.pathsep + os.environ["PYTHONPATH"] if os.environ.get("PYTHONPATH")
                                               else ""), PYTHONDONTWRITEBYTECODE="1")
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", RUNNER, dest, *tests], cwd=dest, env=env, capture_output=True,
                           text=True, timeout=timeout)
        rc, out = p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as e:
        rc, out = None, f"timed out after {timeout} s\n" + (e.stdout or b"").decode(errors="replace")[-2000:]
    seconds = time.perf_counter() - t0
    imported = next((ln.split("imported from ", 1)[1] for ln in out.splitlines() if "orthowarp imported from" in ln),
                    None)
    return rc, out, seconds, imported


def summary(out):
    """The failing test ids and the pytest summary line of a run's output."""
    lines = out.strip().splitlines()
    failed = [ln.split(" - ")[0][len("FAILED "):] for ln in lines if ln.startswith("FAILED ")]
    last = lines[-1] if lines else ""
    # the first failure's error lines: an assertion (a kill) rather than, say, a compile error
    errors = [ln[1:].strip() for ln in lines if ln.startswith("E ")][:4]
    return failed, last + ("" if not errors else " | " + " / ".join(errors))[:600]


def git(*args):
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30).stdout.rstrip()
    except (OSError, subprocess.SubprocessError):
        return None


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write the report as JSON here")
    ap.add_argument("--only", nargs="+", help="run only these mutations (names)")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--timeout", type=int, default=TIMEOUT_S, help="seconds per test run")
    args = ap.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m["name"] in args.only]
    if args.list or not chosen:
        for m in MUTATIONS:
            print(f"{m['name']:36s} {m['file']:22s} {m['what']}")
        return 0 if args.list else 2
    report = dict(benchmark="mutation_check", date=datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec="seconds"), machine=platform.machine(), node=platform.node(), cpu_count=os.cpu_count(),
        python=platform.python_version(), commit=(git("rev-parse", "HEAD") or "").strip() or None,
        checkout_modified=sorted(ln[3:] for ln in (git("status", "--porcelain") or "").splitlines()),
        fuzz_examples=os.environ.get("ORTHOWARP_FUZZ_EXAMPLES", "default"), mutations=[])
    try:
        import warp

        report["warp"] = warp.__version__
    except ImportError:
        pass
    ok = True
    with tempfile.TemporaryDirectory(prefix="orthowarp-mutation-") as dest:
        make_copy(dest)
        check_mutations(dest)
        # the baseline: every chosen test passes on the unmutated copy
        tests = sorted({t for m in chosen for t in m["tests"]})
        print(f"baseline: {len(tests)} test ids on the unmutated copy ...", flush=True)
        rc, out, seconds, imported = run_tests(dest, tests, args.timeout)
        failed, last = summary(out)
        report["baseline"] = dict(passed=rc == 0, returncode=rc, seconds=round(seconds, 1), tests=tests,
                                  imported=imported, failed=failed, summary=last)
        print(f"  {'passed' if rc == 0 else 'FAILED'} in {seconds:.0f} s: {last}", flush=True)
        if rc != 0:
            print(out[-5000:])
            ok = False
        for m in chosen:
            path = copy_path(dest, m["file"])
            with open(path) as f:
                text = f.read()
            try:
                with open(path, "w") as f:
                    f.write(text.replace(m["original"], m["replacement"], 1))
                rc, out, seconds, imported = run_tests(dest, m["tests"], args.timeout)
            finally:
                with open(path, "w") as f:
                    f.write(text)
            status = {1: "killed", 0: "survived"}.get(rc, "error")
            failed, last = summary(out)
            ok &= status == "killed"
            report["mutations"].append(dict(name=m["name"], file=m["file"], what=m["what"], original=m["original"],
                                            replacement=m["replacement"], status=status, returncode=rc,
                                            seconds=round(seconds, 1), tests=m["tests"], failed=failed,
                                            summary=last, imported=imported))
            print(f"{m['name']:36s} {status:8s} {seconds:7.1f} s  {', '.join(failed) or last}", flush=True)
            if status == "error":
                print(out[-3000:])
    width = max(len(m["name"]) for m in report["mutations"]) if report["mutations"] else 10
    print(f"\n{'mutation':{width}s}  status    seconds  tests")
    for m in report["mutations"]:
        print(f"{m['name']:{width}s}  {m['status']:8s} {m['seconds']:8.1f}  {len(m['tests'])}")
    if args.out:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from _report import save_report

        save_report(report, args.out)
        print(f"report: {args.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
