"""``orthowarp mosaic --scheduler tls://...`` on a TLS-secured Dask cluster: the same bytes as
in one process through its certificates; plain connections, unknown certificates and a
``tls://`` address without certificates refused with a one-line error, no output left and no
key material in the messages.

The throwaway certificate authority and the certificate of 127.0.0.1 / localhost (scheduler,
worker and client alike) are made with the ``openssl`` command; the test is skipped where
there is none.
"""

import logging
import os
import shutil
import subprocess
import sys

import pytest
from click.testing import CliRunner
from test_faults import ROOT, _error_line, _frame_job

from orthowarp.cli import main

distributed = pytest.importorskip("distributed")
# (the job's frames have no georeferencing; a TLS LocalCluster: slow, which CI runs too)
pytestmark = [pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning"), pytest.mark.slow]


def _openssl(*args, cwd):
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _make_ca(folder, name):
    """A self-signed CA (``name``-ca.pem, its key ``name``-ca.key) and a certificate/key of
    127.0.0.1 and localhost signed by it (``name``-cert.pem, ``name``-key.pem)."""
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", f"/CN=orthowarp test CA {name}",
             "-keyout", f"{name}-ca.key", "-out", f"{name}-ca.pem",
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
             cwd=folder)
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost", "-keyout", f"{name}-key.pem",
             "-out", f"{name}.csr", cwd=folder)
    (folder / f"{name}.ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n"
                                        "extendedKeyUsage=serverAuth,clientAuth\n")
    _openssl("x509", "-req", "-days", "2", "-in", f"{name}.csr", "-CA", f"{name}-ca.pem", "-CAkey", f"{name}-ca.key",
             "-CAcreateserial", "-extfile", f"{name}.ext", "-out", f"{name}-cert.pem", cwd=folder)
    return dict(ca=str(folder / f"{name}-ca.pem"), cert=str(folder / f"{name}-cert.pem"),
                key=str(folder / f"{name}-key.pem"))


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    """The cluster's CA and certificate, and another CA's (which the cluster does not trust)."""
    if shutil.which("openssl") is None:
        pytest.skip("no openssl command to make the test's certificates")
    folder = tmp_path_factory.mktemp("certs")
    return _make_ca(folder, "cluster"), _make_ca(folder, "stranger")


@pytest.fixture(scope="module")
def tls_cluster(certs):
    """A LocalCluster (one worker process) that speaks TLS only, on 127.0.0.1."""
    from distributed.security import Security

    c, _ = certs
    security = Security(tls_ca_file=c["ca"], tls_scheduler_cert=c["cert"], tls_scheduler_key=c["key"],
                        tls_worker_cert=c["cert"], tls_worker_key=c["key"], tls_client_cert=c["cert"],
                        tls_client_key=c["key"], require_encryption=True)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  protocol="tls://", security=security, dashboard_address="127.0.0.1:0",
                                  silence_logs=logging.ERROR) as cluster:
        assert cluster.scheduler_address.startswith("tls://127.0.0.1:")
        with distributed.Client(cluster) as client:  # (the cluster's own security)
            client.wait_for_workers(1)
        yield cluster


@pytest.fixture
def job(tmp_path):
    """The two-frame job of test_cluster.test_cli_tiled_mosaic_and_runs_on_a_scheduler."""
    args = _frame_job(tmp_path, "a")
    shutil.copy(tmp_path / "a.tif", tmp_path / "b.tif")
    with open(tmp_path / "ext.csv", "a") as f:
        f.write("b,500015,5200000,600,1,-2,30\n")
    return [args[0], str(tmp_path / "b.tif"), *args[1:], "--resolution", "0.5", "--tile-size", "32"]


def _tls_args(c):
    return ["--tls-ca-file", c["ca"], "--tls-cert", c["cert"], "--tls-key", c["key"]]


def _assert_no_key_material(text, *cs):
    """No line of the PEM files (certificates or keys) in ``text``."""
    for c in cs:
        for path in c.values():
            with open(path) as f:
                for line in f.read().splitlines():
                    assert line not in text, f"{os.path.basename(path)} content in the output"
    assert "PRIVATE KEY" not in text and "BEGIN" not in text


def _files(folder):
    out = {}
    for sub in ("tiles", "index"):
        d = os.path.join(folder, sub)
        for name in sorted(os.listdir(d)):
            with open(os.path.join(d, name), "rb") as f:
                out[f"{sub}/{name}"] = f.read()
    return out


def test_a_tls_cluster_runs_the_cli_and_gives_the_same_bytes(certs, tls_cluster, job, tmp_path):
    """The single COG (and its index) and the tiled product, computed on the TLS cluster's worker:
    byte for byte what this process writes."""
    c, _ = certs
    address = tls_cluster.scheduler_address
    run = CliRunner().invoke
    here, there = tmp_path / "here", tmp_path / "there"
    res = run(main, ["mosaic", *job, "--out", str(here / "m.tif"), "--index", str(here / "i.tif")])
    assert res.exit_code == 0, res.output
    res = run(main, ["mosaic", *job, "--out", str(there / "m.tif"), "--index", str(there / "i.tif"),
                     "--scheduler", address, *_tls_args(c)])
    assert res.exit_code == 0, res.output
    assert "Dask cluster: 1 worker(s)" in res.output
    outputs = [res.output]
    for name in ("m.tif", "i.tif"):
        assert (here / name).read_bytes() == (there / name).read_bytes(), name
    # the tiled product, its tiles written by the worker
    res = run(main, ["mosaic", *job, "--out", str(here / "t"), "--tiled", "--product-tile", "64"])
    assert res.exit_code == 0, res.output
    res = run(main, ["mosaic", *job, "--out", str(there / "t"), "--tiled", "--product-tile", "64",
                     "--scheduler", address, *_tls_args(c)])
    assert res.exit_code == 0, res.output
    outputs.append(res.output)
    assert _files(here / "t") == _files(there / "t") != {}
    assert (here / "t" / "mosaic.vrt").read_text() == (there / "t" / "mosaic.vrt").read_text()
    _assert_no_key_material("\n".join(outputs), *certs)


def test_a_tls_cluster_refuses_plain_and_unknown_clients(certs, tls_cluster, job, tmp_path):
    """A plain tcp:// connection, and a client whose certificate another CA signed: a one-line
    error, exit code 1, no output; the TLS options without a tls:// address are refused before
    any connection."""
    import dask

    c, stranger = certs  # (c: the TLS options given with a tcp:// address)
    address = tls_cluster.scheduler_address
    plain = "tcp://" + address[len("tls://"):]
    run = CliRunner().invoke
    out = tmp_path / "out"
    outputs = []
    with dask.config.set({"distributed.comm.timeouts.connect": "5s"}):
        for scheduler, tls in ((address, _tls_args(stranger)), (plain, [])):
            for tiled in ([], ["--tiled"]):
                res = run(main, ["mosaic", *job, "--out", str(out), *tiled, "--scheduler", scheduler, *tls])
                assert res.exit_code == 1, res.output
                says = f"Error: Could not connect to the Dask scheduler '{scheduler}'"
                assert _error_line(res.output).startswith(says), res.output
                assert not os.path.exists(out) and not os.path.exists(f"{out}.partial"), tiled
                outputs.append(res.output)
    res = run(main, ["mosaic", *job, "--out", str(out), "--scheduler", plain, *_tls_args(c)])
    assert res.exit_code == 1 and "go with --scheduler tls://" in _error_line(res.output)
    outputs.append(res.output)
    assert not os.path.exists(out)
    _assert_no_key_material("\n".join(outputs), *certs)


def test_a_tls_address_without_certificates_is_a_one_line_error(tls_cluster, job, tmp_path):
    """``--scheduler tls://...`` without the TLS options (and no TLS in Dask's configuration):
    a one-line error, exit code 1, no output. In a subprocess: a Dask client that failed that
    way can deadlock the next client made in its process."""
    (tmp_path / "dask-config").mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    env.update(DASK_CONFIG=str(tmp_path / "dask-config"), DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT="5s")
    out = tmp_path / "out.tif"
    p = subprocess.run([sys.executable, "-m", "orthowarp.cli", "mosaic", *job, "--out", str(out),
                        "--scheduler", tls_cluster.scheduler_address], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 1, p.stderr
    line = _error_line(p.stderr)
    assert f"'{tls_cluster.scheduler_address}'" in line, line
    assert not out.exists()
