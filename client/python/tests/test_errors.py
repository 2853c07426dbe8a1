"""decima_client's bad inputs of issue 33 against a real decima-server on loopback and the real
`decima` CLI: a bad spec, a wrong token, a missing file, an unreachable server, a server that
never answers or stops answering, an upload over the limit, refused TLS handshakes. Each raises
a typed error whose text is the line the CLI prints for the same failure, and nothing hangs."""
import gzip
import os
import shutil
import signal
import socket
import struct
import subprocess
import time

import pytest

import decima_client
from decima_client import errors
from decima_client.proto import jobs_pb2

from conftest import (QUICK, TOKEN, Server, first_line, free_port, run_cli, volume_names,
                      write_tiny_nifti)


def test_a_bad_spec_raises_invalid_argument_with_the_field_as_the_cli(client, cli_bin, server,
                                                                      tmp_path):
    nii = write_tiny_nifti(tmp_path / "bad.nii", seed=6)
    before = volume_names(client)
    with pytest.raises(errors.InvalidArgument) as e:
        client.submit(nii, regions=99)
    assert e.value.detail.field == "spec.regions"
    assert e.value.code.name == "INVALID_ARGUMENT"
    rc, _, err = run_cli(cli_bin, server.address, ["submit", nii, "--regions", "99"])
    assert str(e.value) in err.splitlines(), err
    assert e.value.exit_code == rc == 1
    # The volume made for the refused job is deleted again, as the CLI does.
    assert volume_names(client) == before


def test_spec_mistakes_are_refused_before_anything_is_sent(client, tmp_path):
    nii = write_tiny_nifti(tmp_path / "s.nii", seed=7)
    before = volume_names(client)
    with pytest.raises(errors.InputError, match="unknown job parameter 'regoins'"):
        client.submit(nii, regoins=3)
    with pytest.raises(errors.InputError, match="policy='fast': not one of paper"):
        client.submit(nii, policy="fast")
    with pytest.raises(errors.InputError, match="regions='three'"):
        client.submit(nii, regions="three")
    with pytest.raises(errors.InputError, match="unknown weight 'w_x'"):
        client.submit(nii, weights={"w_x": 1})
    for bad in (float("nan"), float("inf"), -5.0, 0):
        with pytest.raises(errors.InputError, match="min_psnr=.*finite and > 0"):
            client.submit(nii, min_psnr=bad)
    assert volume_names(client) == before


def test_a_wrong_token_raises_unauthenticated_as_the_cli(server, cli_bin, tmp_path):
    nii = write_tiny_nifti(tmp_path / "t.nii", seed=8)
    wrong = decima_client.Client(server.address, token="not-the-token", timeout=10)
    with pytest.raises(errors.Unauthenticated) as e:
        wrong.submit(nii)
    rc, _, err = run_cli(cli_bin, server.address, ["submit", nii], token="not-the-token")
    assert str(e.value) in err.splitlines(), err
    assert e.value.exit_code == rc == 7
    with pytest.raises(errors.Unauthenticated):
        wrong.list()
    with pytest.raises(errors.Unauthenticated):  # no token at all
        decima_client.Client(server.address, token="", timeout=10).list()


def test_a_missing_file_raises_missing_input_error_as_the_cli(client, cli_bin, server, tmp_path):
    missing = str(tmp_path / "no-such-scan.nii.gz")
    with pytest.raises(errors.MissingInputError) as e:
        client.submit(missing, regions=3)
    assert isinstance(e.value, FileNotFoundError)
    rc, _, err = run_cli(cli_bin, server.address, ["submit", missing, "--regions", "3"])
    assert str(e.value) == first_line(err) == f"decima: {missing}: no such file or folder"
    assert e.value.exit_code == rc == 2


def test_an_unreachable_server_fails_fast_as_the_cli(cli_bin, tmp_path):
    port = free_port()
    address = f"127.0.0.1:{port}"
    client = decima_client.Client(address, timeout=30)
    start = time.monotonic()
    with pytest.raises(errors.ServerUnreachable) as e:
        client.list()
    took = time.monotonic() - start
    assert took < 6, took  # at most min(5 s, timeout) for the connection, never the 30 s
    ours = first_line(str(e.value))
    rc, _, err = run_cli(cli_bin, address, ["list"], token="")
    theirs = first_line(err)
    # The same words; only where the address came from differs (--server vs Client(address)).
    prefix = f"decima: list: cannot reach decima-server at {address} ("
    suffix = "): connection refused or failed"
    assert ours.startswith(prefix) and ours.endswith(suffix), ours
    assert theirs.startswith(prefix) and theirs.endswith(suffix), theirs
    assert e.value.exit_code == rc == 8
    # submit and watch fail the same way (a submit checks its input first).
    nii = write_tiny_nifti(tmp_path / "u.nii")
    with pytest.raises(errors.ServerUnreachable, match="decima: submit: cannot reach"):
        client.submit(nii)


def test_a_server_that_never_answers_fails_within_the_deadline_as_the_cli(cli_bin):
    # A socket that listens (the kernel completes the TCP handshake) but never speaks HTTP/2.
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        address = "127.0.0.1:%d" % silent.getsockname()[1]
        client = decima_client.Client(address, timeout=2)
        start = time.monotonic()
        with pytest.raises(errors.ServerUnreachable) as e:
            client.list()
        assert time.monotonic() - start < 5
        rc, _, err = run_cli(cli_bin, address, ["--timeout", "2", "list"], token="")
    ours, theirs = first_line(str(e.value)), first_line(err)
    assert ours.endswith("): no answer within 0:02"), ours
    assert theirs.endswith("): no answer within 0:02"), theirs
    assert ours.split(" (")[0] == theirs.split(" (")[0]
    assert e.value.exit_code == rc == 8


def test_a_server_that_stops_answering_mid_watch_raises_deadline_exceeded(server_bin, tmp_path):
    srv = Server(server_bin, str(tmp_path))
    try:
        client = decima_client.Client(srv.address, token=TOKEN, timeout=2, reconnect=5)
        client._create_job_metadata = (("decima-test-fault", "sleep:60"),)
        job = client.submit(write_tiny_nifti(tmp_path / "h.nii", seed=11), **QUICK)
        events = job.watch()
        next(events)  # the snapshot: the stream is up
        os.kill(srv.proc.pid, signal.SIGSTOP)  # the connection stays open, nothing answers
        start = time.monotonic()
        try:
            with pytest.raises(errors.DeadlineExceeded, match=f"watch {job.name}: DEADLINE"):
                for _ in events:
                    pass
            took = time.monotonic() - start
            # One stream's deadline, then a new stream that gets not even the snapshot.
            assert took < 3 * 2 + 2, took
            with pytest.raises(errors.DeadlineExceeded):
                client.list()
        finally:
            os.kill(srv.proc.pid, signal.SIGCONT)
        client.cancel(job)
        client.close()
    finally:
        srv.stop()  # SIGTERM: the server stops its job processes too


def test_an_upload_over_the_servers_limit_carries_the_limit_in_the_error_detail(server_bin,
                                                                               cli_bin,
                                                                               tmp_path):
    srv = Server(server_bin, str(tmp_path), extra=["--max-upload-mb", "1"])
    try:
        big = tmp_path / "big.nii"
        big.write_bytes(os.urandom(3 << 19))  # 1.5 MiB: refused on its declared size
        client = decima_client.Client(srv.address, token=TOKEN, timeout=10)
        with pytest.raises(errors.InvalidArgument) as e:
            client.submit(str(big))
        assert e.value.detail.field == "size_bytes"
        assert (e.value.detail.limit, e.value.detail.limit_value) == ("max_upload_mb", 1)
        rc, _, err = run_cli(cli_bin, srv.address, ["submit", str(big)])
        assert str(e.value) in err.splitlines(), err
        assert e.value.exit_code == rc == 1
        client.close()
    finally:
        srv.stop()


def _write_nifti_gz_zeros(path, nx, ny, nz, nifti2=False):
    """A gzipped NIfTI (1 or 2) of uint8 zeros: a small file that declares a big volume."""
    if nifti2:
        hdr = bytearray(544)
        struct.pack_into("<i", hdr, 0, 540)
        hdr[4:12] = b"n+2\0\r\n\x1a\n"
        struct.pack_into("<hh", hdr, 12, 2, 8)  # uint8
        struct.pack_into("<8q", hdr, 16, 3, nx, ny, nz, 1, 1, 1, 1)
        struct.pack_into("<4d", hdr, 104, 1.0, 1.0, 1.0, 1.0)
        struct.pack_into("<q", hdr, 168, 544)  # vox_offset
    else:
        hdr = bytearray(352)
        struct.pack_into("<i", hdr, 0, 348)
        struct.pack_into("<8h", hdr, 40, 3, nx, ny, nz, 1, 1, 1, 1)
        struct.pack_into("<hh", hdr, 70, 2, 8)  # uint8
        struct.pack_into("<4f", hdr, 76, 1.0, 1.0, 1.0, 1.0)
        struct.pack_into("<f", hdr, 108, 352.0)
        hdr[344:348] = b"n+1\0"
    zeros = bytes(1 << 20)
    with gzip.open(path, "wb", compresslevel=1) as f:
        f.write(bytes(hdr))
        left = nx * ny * nz
        while left > 0:
            n = min(left, len(zeros))
            f.write(zeros[:n])
            left -= n
    return str(path)


def test_the_header_reader_reads_every_format_and_refuses_broken_headers(tmp_path):
    from decima_client import _header
    assert _header.read_dims(write_tiny_nifti(tmp_path / "t.nii")) == (12, 10, 8)
    gz = _write_nifti_gz_zeros(tmp_path / "z.nii.gz", 20, 6, 4)
    assert _header.read_dims(gz) == (20, 6, 4)
    assert _header.read_dims(_write_nifti_gz_zeros(tmp_path / "z2.nii.gz", 7, 5, 3,
                                                   nifti2=True)) == (7, 5, 3)
    (tmp_path / "a.mha").write_bytes(b"ObjectType = Image\nNDims = 3\nDimSize = 9 8 7\n"
                                     b"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n"
                                     + bytes(9 * 8 * 7))
    assert _header.read_dims(tmp_path / "a.mha") == (9, 8, 7)
    (tmp_path / "a.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 5 4 3\n"
                                      b"encoding: raw\n\n" + bytes(60))
    assert _header.read_dims(tmp_path / "a.nrrd") == (5, 4, 3)
    # Broken: each None (submit then uploads and the server names the problem), never a raise.
    nii = open(write_tiny_nifti(tmp_path / "b.nii"), "rb").read()
    bad = {
        "truncated.nii": nii[:100],
        "magic.nii": b"\0" * 352,
        "zero.nii": nii[:42] + struct.pack("<h", 0) + nii[44:],
        "negative.nii": nii[:42] + struct.pack("<h", -5) + nii[44:],
        "garbage.nii.gz": b"\x1f\x8b" + os.urandom(200),
        "nodims.mha": b"ObjectType = Image\nElementDataFile = LOCAL\n",
        "text.mha": b"DimSize = a b c\n",
        "negative.nrrd": b"NRRD0004\nsizes: 5 -4 3\n\n",
        "magic.nrrd": b"NOPE\nsizes: 5 4 3\n\n",
        "empty.nrrd": b"",
    }
    for name, data in bad.items():
        (tmp_path / name).write_bytes(data)
        assert _header.read_dims(tmp_path / name) is None, name
    assert _header.read_dims(tmp_path) is None  # a folder (DICOM): not checked


def test_a_job_over_the_memory_limit_is_refused_before_any_upload_as_the_cli(server_bin, cli_bin,
                                                                            tmp_path):
    work = tmp_path / "server"
    work.mkdir()
    srv = Server(server_bin, str(work), extra=["--worker-memory-mb", "2048"])
    try:
        big = _write_nifti_gz_zeros(tmp_path / "big.nii.gz", 512, 512, 256)
        client = decima_client.Client(srv.address, token=TOKEN, timeout=30)
        with pytest.raises(errors.ResourceExhausted) as e:
            client.submit(big)
        assert "big.nii.gz (512x512x256 voxels) needs about" in str(e.value)
        assert "--worker-memory-mb" in str(e.value)
        assert e.value.detail.field == "dims"
        assert (e.value.detail.limit, e.value.detail.limit_value) == ("worker_memory_mb", 2048)
        # Nothing went up: no blob, no partial upload, no volume.
        for sub in ("sha256", "partial"):
            folder = os.path.join(srv.data_dir, "blobs", sub)
            assert not os.path.isdir(folder) or not any(
                files for _, _, files in os.walk(folder)), sub
        assert volume_names(client) == set()
        rc, _, err = run_cli(cli_bin, srv.address, ["submit", big])
        assert rc == e.value.exit_code == 1, err
        assert "big.nii.gz (512x512x256 voxels) needs about" in err
        # A job that fits goes up as before.
        job = client.submit(write_tiny_nifti(tmp_path / "small.nii", seed=31), **QUICK)
        assert job.name.startswith("jobs/")
        client.close()
    finally:
        srv.stop()


def _make_pki(folder):
    """A throwaway CA and a server certificate for 127.0.0.1, made with the openssl command."""
    def openssl(*args):
        subprocess.run(["openssl"] + list(args), cwd=folder, check=True, capture_output=True,
                       timeout=60)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "1", "-subj",
            "/CN=decima-test-ca")
    openssl("req", *ec, "-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=127.0.0.1")
    (folder / "ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
            "-CAcreateserial", "-out", "server.pem", "-days", "1", "-extfile", "ext")


def test_tls_with_the_servers_ca_and_refused_handshakes(server_bin, tmp_path, monkeypatch):
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed")
    pki = tmp_path / "pki"
    pki.mkdir()
    _make_pki(pki)
    srv = Server(server_bin, str(tmp_path),
                 extra=["--tls-cert", str(pki / "server.pem"),
                        "--tls-key", str(pki / "server.key")])
    try:
        with decima_client.Client(srv.address, token=TOKEN, ca_cert=str(pki / "ca.pem"),
                                  timeout=10) as tls:
            assert isinstance(tls.list(), list)
        # DECIMA_CA_CERT is the default of ca_cert, as of the CLI's --ca-cert.
        monkeypatch.setenv("DECIMA_CA_CERT", str(pki / "ca.pem"))
        with decima_client.Client(srv.address, token=TOKEN, timeout=10) as from_env:
            assert isinstance(from_env.list(), list)
        monkeypatch.delenv("DECIMA_CA_CERT")
        # The system's roots do not know the test CA: a refused handshake, said so.
        with pytest.raises(errors.ServerUnreachable, match="refused handshake"):
            decima_client.Client(srv.address, token=TOKEN, tls=True, timeout=5).list()
        with pytest.raises(errors.ServerUnreachable):  # plaintext to a TLS server
            decima_client.Client(srv.address, token=TOKEN, timeout=5).list()
        with pytest.raises(errors.InputError, match="ca_cert .*no-such-ca.pem: cannot read"):
            decima_client.Client(srv.address, ca_cert=str(tmp_path / "no-such-ca.pem"))
    finally:
        srv.stop()


def test_watching_an_unknown_job_raises_not_found_as_the_cli(client, cli_bin, server):
    name = "jobs/00000000deadbeef"
    job = decima_client.Job(client, jobs_pb2.Job(name=name))
    with pytest.raises(errors.NotFound) as e:
        list(job.watch())
    rc, _, err = run_cli(cli_bin, server.address, ["watch", name])
    assert str(e.value) in err.splitlines(), err
    assert e.value.exit_code == rc == 6


def test_wait_with_a_timeout_raises_deadline_exceeded_and_the_job_goes_on(client, tmp_path):
    client._create_job_metadata = (("decima-test-fault", "sleep:60"),)
    job = client.submit(write_tiny_nifti(tmp_path / "d.nii", seed=16), **QUICK)
    start = time.monotonic()
    with pytest.raises(errors.DeadlineExceeded, match="the job goes on on the server"):
        job.wait(timeout=1)
    # Checked at every event, heartbeats included (the server sends one a second here).
    assert time.monotonic() - start < 1 + 3
    assert job.refresh().state in ("QUEUED", "RUNNING")
    assert client.cancel(job).state == "CANCELLED"
