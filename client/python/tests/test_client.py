"""decima_client against a real decima-server on loopback, the paths of a job: submit (a file,
a MetaImage header, a DICOM folder, a retried request id), watch (also across a server
restart), wait, fetch (also resumed), the numpy arrays, list, cancel, delete, series, and the
README's notebook example. The bad inputs are in test_errors.py."""
import gzip
import json
import os
import re
import shutil
import signal
import subprocess
import threading
import time

import pytest

import decima_client
from decima_client import errors
from decima_client.proto import jobs_pb2, volumes_pb2

from conftest import (QUICK, TOKEN, Server, first_line, free_port, run_cli, sha256,
                      write_tiny_nifti)


def test_submit_watch_wait_and_fetch_a_tiny_volume(client, tmp_path):
    nii = write_tiny_nifti(tmp_path / "tiny.nii", seed=1)
    job = client.submit(nii, **QUICK)
    assert job.name.startswith("jobs/")

    events = list(job.watch())
    assert events[0].WhichOneof("kind") == "snapshot"
    sequences = [e.sequence for e in events[1:]]
    # Every stored and live event once, in order, no gap: 1, 2, 3, ...
    assert sequences == list(range(1, len(sequences) + 1)), sequences
    assert sum(e.WhichOneof("kind") == "progress" for e in events) >= 1
    assert events[-1].state_change.state == jobs_pb2.SUCCEEDED
    assert job.state == "SUCCEEDED"
    # The overall fraction (the CLI's bar) never goes back and ends at 1.
    overall = [decima_client.overall_fraction(e.progress) for e in events
               if e.WhichOneof("kind") == "progress"]
    assert overall == sorted(overall) and overall[-1] == pytest.approx(1.0), overall
    assert job.overall == 1.0

    assert job.wait(timeout=30) is job  # a final job: wait returns at once

    out = tmp_path / "out"
    paths = job.fetch(out)
    names = sorted(os.path.basename(p) for p in paths)
    expected = sorted({a.file_name for a in job.proto.artifacts} | {"metrics.json"})
    assert names == expected
    for a in job.proto.artifacts:
        assert sha256(out / a.file_name) == a.sha256
        assert os.path.getsize(out / a.file_name) == a.size_bytes
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == job.metrics
    assert metrics["simplification"]["achieved_reduction"] > 0
    assert not list(out.glob("*.part"))

    # Only some outputs, by kind and by name.
    only = job.fetch(tmp_path / "only", outputs=["vtu", "metrics.json"])
    assert sorted(os.path.basename(p) for p in only) == ["mesh.vtu", "metrics.json"]


def test_an_interrupted_fetch_resumes_from_the_part_file(client, tmp_path):
    job = client.submit(write_tiny_nifti(tmp_path / "r.nii", seed=2), **QUICK).wait(timeout=120)
    mesh = next(a for a in job.proto.artifacts if a.file_name == "mesh.vtu")
    full = job.fetch(tmp_path / "full", outputs="vtu")[0]
    out = tmp_path / "resumed"
    out.mkdir()
    with open(full, "rb") as f:
        head = f.read(mesh.size_bytes // 2)
    (out / "mesh.vtu.part").write_bytes(head)
    [path] = job.fetch(out, outputs="vtu")
    assert sha256(path) == mesh.sha256
    assert not (out / "mesh.vtu.part").exists()

    # A .part that does not match the server's bytes is caught by the sha256, not kept.
    (out / "mesh.vtu").unlink()
    (out / "mesh.vtu.part").write_bytes(b"x" * len(head))
    with pytest.raises(errors.DataLoss, match="do not match the server's size/sha256"):
        job.fetch(out, outputs="vtu")
    assert not (out / "mesh.vtu.part").exists()


def test_watch_reconnects_across_a_server_restart_and_misses_no_event(server_bin, tmp_path):
    port = free_port()
    srv = Server(server_bin, str(tmp_path), port=port)
    try:
        client = decima_client.Client(srv.address, token=TOKEN, timeout=10, reconnect=60)
        # The fault seam: a cancellable 3 s "prepare" stage with progress every 50 ms.
        client._create_job_metadata = (("decima-test-fault", "sleep:3"),)
        job = client.submit(write_tiny_nifti(tmp_path / "w.nii", seed=3), **QUICK)
        events, restarted = [], False
        for ev in job.watch():
            events.append(ev)
            if not restarted and sum(e.WhichOneof("kind") == "progress" for e in events) >= 3:
                # SIGTERM with --drain-seconds 0: the running job is requeued, the stream ends.
                srv.stop(signal.SIGTERM)
                srv.start()  # the same port and data dir
                restarted = True
        assert restarted
        assert job.state == "SUCCEEDED", job.proto
        # It really ran again after the restart: RUNNING twice, the stages started over.
        running = [e for e in events if e.WhichOneof("kind") == "state_change"
                   and e.state_change.state == jobs_pb2.RUNNING]
        assert len(running) == 2, [e.WhichOneof("kind") for e in events]
        sequences = [e.sequence for e in events[1:]]
        assert sequences == list(range(1, len(sequences) + 1)), sequences
        client.close()
    finally:
        srv.stop()  # SIGTERM: the server stops its job processes too


def test_cancel_stops_a_running_job_and_wait_raises_job_cancelled(client, tmp_path):
    client._create_job_metadata = (("decima-test-fault", "sleep:60"),)
    job = client.submit(write_tiny_nifti(tmp_path / "c.nii", seed=4), **QUICK)
    for ev in job.watch():
        if ev.WhichOneof("kind") == "progress":
            break  # running
    cancelled = client.cancel(job)
    assert cancelled.state == "CANCELLED"
    with pytest.raises(errors.JobCancelled) as e:
        job.wait(timeout=30)
    assert str(e.value).startswith(f"decima: {job.name} CANCELLED")
    assert e.value.exit_code == 4
    with pytest.raises(errors.JobCancelled, match=f"fetch {job.name}: the job is CANCELLED"):
        job.fetch(tmp_path / "nothing")

    job.delete()
    with pytest.raises(errors.NotFound) as nf:
        client.job(job.name)
    assert nf.value.exit_code == 6


def test_list_shows_the_jobs_as_the_cli_does(client, cli_bin, server, tmp_path):
    job = client.submit(write_tiny_nifti(tmp_path / "l.nii", seed=5), **QUICK).wait(timeout=120)
    listed = client.list()
    assert job.name in [j.name for j in listed]
    rc, out, err = run_cli(cli_bin, server.address, ["list", "-o", "json"])
    assert rc == 0, err
    assert [j.name for j in listed] == [json.loads(l)["name"] for l in out.splitlines()]
    assert all(j.state == "SUCCEEDED" for j in client.list(states=["succeeded"]))
    assert job.name in [j.name for j in client.list(states=["succeeded"])]
    assert job.name not in [j.name for j in client.list(states=[jobs_pb2.FAILED])]
    # A unique prefix of the id names the job, as in the CLI.
    assert client.job(job.name[len("jobs/"):][:8]).name == job.name


def test_series_lists_what_the_receiver_got(client, cli_bin, server):
    # This server has no DICOM receiver: nothing received, and the CLI agrees.
    assert client.series() == []
    rc, _, err = run_cli(cli_bin, server.address, ["series"])
    assert rc == 0 and "no series received" in err


def test_series_carry_the_id_of_the_association_that_brought_them(server_bin, tmp_path):
    # One slice of the shared series by the real storescu, twice: two associations, each with
    # the id the server logged when it accepted it; the newest receive shows the second's.
    storescu = "/usr/bin/storescu"
    series = os.path.join(os.environ.get("DECIMA_SHARED_DATA", ""), "ct-head-256x256x113-dicom")
    if not os.access(storescu, os.X_OK):
        pytest.skip("storescu (Debian package dcmtk) is not installed")
    if not os.path.isdir(series):
        pytest.skip(f"the shared DICOM series is absent ({series})")
    slice_file = os.path.join(series, sorted(n for n in os.listdir(series)
                                             if n.endswith(".dcm"))[0])
    dicom_port = free_port()
    srv = Server(server_bin, str(tmp_path), port=free_port(),
                 extra=["--dicom-listen", f"127.0.0.1:{dicom_port}", "--dicom-min-free-mb", "0",
                        "--dicom-quiet-seconds", "0.2"])
    try:
        client = decima_client.Client(srv.address, token=TOKEN, timeout=10)
        ids = []
        for _ in range(2):
            subprocess.run([storescu, "-aet", "CT1", "-aec", "DECIMA", "127.0.0.1",
                            str(dicom_port), slice_file], check=True, timeout=60,
                           capture_output=True)
            accepted = re.findall(r"association ([0-9a-f]{16}) accepted from 127\.0\.0\.1: "
                                  r"calling AE 'CT1'", (tmp_path / "server.log").read_text())
            assert len(accepted) == len(ids) + 1, srv.read_log()
            ids.append(accepted[-1])
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                listed = client.series()
                if listed and listed[0].state != volumes_pb2.ReceivedSeries.RECEIVING:
                    break
                time.sleep(0.1)
            assert listed and listed[0].association_id == ids[-1], listed
        assert ids[0] != ids[1]
        # The re-sent slice is the same instance: the receive of the second association.
        assert [r.association_id for r in client.series()][0] == ids[1]
        client.close()
    finally:
        srv.stop()


def test_fetch_with_a_reduction_takes_the_level_from_the_jobs_record(client, tmp_path):
    path = write_tiny_nifti(tmp_path / "f.nii", seed=9)
    spec = dict(QUICK, outputs=["vtu", "levels"])
    recorded = client.submit(path, **dict(spec, target_reduction=0.3)).wait(timeout=120)
    direct = client.submit(path, **dict(spec, target_reduction=0.6)).wait(timeout=120)
    paths = recorded.fetch(tmp_path / "lod", ["vtu", "metrics"], reduction=0.6)
    assert sorted(os.path.basename(p) for p in paths) == ["mesh.vtu", "metrics.json"]
    direct_paths = direct.fetch(tmp_path / "direct", ["vtu"])
    with open(tmp_path / "lod" / "mesh.vtu", "rb") as a, open(direct_paths[0], "rb") as b:
        assert a.read() == b.read()
    level = recorded.level(0.5, ["msh"])
    assert level.proto.spec.levels_of == recorded.name
    assert level.metrics["simplification"]["from_levels"] is True
    assert [a.file_name for a in level.proto.artifacts] == ["mesh.msh", "metrics.json"]
    # A job without a record: refused by the server, saying how to get one.
    plain = client.submit(path, **QUICK).wait(timeout=120)
    with pytest.raises(errors.FailedPrecondition, match="kept no level record"):
        plain.fetch(tmp_path / "none", reduction=0.5)
    assert not (tmp_path / "none").exists()


def test_a_failed_job_raises_job_failed_with_the_server_reason(client, tmp_path):
    client._create_job_metadata = (("decima-test-fault", "crash"),)
    job = client.submit(write_tiny_nifti(tmp_path / "x.nii", seed=10), **QUICK)
    with pytest.raises(errors.JobFailed) as e:
        job.wait(timeout=120)
    assert e.value.job.state == jobs_pb2.FAILED
    assert e.value.job.error.message and e.value.job.error.message in str(e.value)
    assert e.value.exit_code == 3


def test_a_metaimage_header_goes_up_with_its_data_file(client, tmp_path):
    nii = write_tiny_nifti(tmp_path / "m.nii", seed=12)
    with open(nii, "rb") as f:
        raw = f.read()[352:]
    (tmp_path / "m.raw").write_bytes(raw)
    (tmp_path / "m.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nDimSize = 12 10 8\nElementType = MET_SHORT\n"
        "ElementSpacing = 2 2 2\nElementDataFile = m.raw\n")
    job = client.submit(str(tmp_path / "m.mhd"), **QUICK)
    vol = client._volumes.GetVolume(volumes_pb2.GetVolumeRequest(name=job.proto.spec.volume),
                                    timeout=10, metadata=client._metadata())
    assert sorted(f.path for f in vol.files) == ["m.mhd", "m.raw"]
    assert list(vol.dims) == [12, 10, 8]
    assert job.wait(timeout=120).state == "SUCCEEDED"
    (tmp_path / "m2.mhd").write_text("ObjectType = Image\nElementDataFile = ../elsewhere.raw\n")
    with pytest.raises(errors.InputError, match="outside the header's folder"):
        client.submit(str(tmp_path / "m2.mhd"))


def test_the_label_map_and_the_mesh_come_as_numpy_arrays(client, tmp_path):
    numpy = pytest.importorskip("numpy")
    pytest.importorskip("vtkmodules")
    job = client.submit(write_tiny_nifti(tmp_path / "a.nii", seed=13), **QUICK).wait(timeout=120)
    labels = job.label_map()
    assert labels.shape == (12, 10, 8)
    # Against the file's own bytes, read without VTK: the same voxels in the same order.
    import struct
    [path] = job.fetch(tmp_path / "raw", outputs="labels")
    with open(path, "rb") as f:
        raw = gzip.decompress(f.read())
    dims = struct.unpack_from("<4h", raw, 40)
    datatype, bitpix = struct.unpack_from("<hh", raw, 70)
    offset = int(struct.unpack_from("<f", raw, 108)[0])
    assert dims[:4] == (3, 12, 10, 8) and (datatype, bitpix) == (2, 8)  # uint8
    expected = numpy.frombuffer(raw, numpy.uint8, 12 * 10 * 8, offset).reshape(8, 10, 12)
    assert (labels == expected.transpose(2, 1, 0)).all()
    assert list(numpy.bincount(labels.ravel())) == job.metrics["segmentation"]["region_voxels"]

    mesh = job.mesh(tmp_path / "mesh")
    assert (tmp_path / "mesh" / "mesh.vtu").exists()
    assert mesh["tets"].shape == (job.metrics["simplification"]["cells_after"], 4)
    assert mesh["points"].shape[1] == 3
    assert 0 <= mesh["tets"].min() and mesh["tets"].max() < len(mesh["points"])
    assert len(mesh["region"]) == len(mesh["tets"])
    assert set(numpy.unique(mesh["label"])) <= {0, 1}
    # Patient coordinates in mm: the grid of voxel centres spans 11 x 9 x 7 voxels of 2 mm.
    span = mesh["points"].max(axis=0) - mesh["points"].min(axis=0)
    assert numpy.allclose(span, [22, 18, 14]), span

    # Without VTK (or numpy) the arrays are a typed error that says what to install.
    import sys
    saved = sys.modules.get("vtkmodules.util")
    sys.modules["vtkmodules.util"] = None
    try:
        with pytest.raises(errors.MissingDependencyError, match="python3-vtk9"):
            job.mesh()
    finally:
        if saved is None:
            del sys.modules["vtkmodules.util"]
        else:
            sys.modules["vtkmodules.util"] = saved


def test_a_retried_submit_with_a_request_id_returns_the_same_job(client, tmp_path):
    nii = write_tiny_nifti(tmp_path / "i.nii", seed=14)
    first = client.submit(nii, request_id="pytest-request-1", **QUICK)
    again = client.submit(nii, request_id="pytest-request-1", **QUICK)
    assert again.name == first.name
    assert again.proto.spec.volume == first.proto.spec.volume  # the volume's id is derived too
    with pytest.raises(errors.AlreadyExists, match=first.name):  # same id, another spec
        client.submit(nii, request_id="pytest-request-1", regions=3)
    first.wait(timeout=120)


def test_unary_calls_ride_out_a_server_restart(server_bin, tmp_path):
    srv = Server(server_bin, str(tmp_path), port=free_port())
    try:
        client = decima_client.Client(srv.address, token=TOKEN, timeout=10, reconnect=30)
        assert client.list() == []  # connected once: from now on UNAVAILABLE is a restart
        srv.stop()
        back = []
        restart = threading.Timer(1.0, lambda: (srv.start(), back.append(time.monotonic())))
        restart.start()
        try:
            assert client.list() == []  # retried until the server is back
            answered = time.monotonic()
        finally:
            restart.join(timeout=40)
        assert back and answered > back[0]
        # Found again within the retry pause (at most 2 s), not after gRPC's own backoff.
        assert answered - back[0] < 4, answered - back[0]
        client.close()
    finally:
        srv.stop()  # SIGTERM: the server stops its job processes too


def test_a_dicom_folder_goes_up_as_the_cli_sends_it(client, cli_bin, server, tmp_path):
    series = os.path.join(os.environ.get("DECIMA_SHARED_DATA", ""), "ct-head-256x256x113-dicom")
    if not os.path.isdir(series):
        pytest.skip(f"the shared DICOM series is absent ({series})")
    folder = tmp_path / "series"
    shutil.copytree(series, folder)
    (folder / "notes.txt").write_text("scanned on the old CT\n")  # no DICM marker: skipped
    (folder / "DICOMDIR").write_bytes(b"a directory record, not an image")
    job = client.submit(str(folder), **QUICK)
    ours = client._volumes.GetVolume(volumes_pb2.GetVolumeRequest(name=job.proto.spec.volume),
                                     timeout=10, metadata=client._metadata())
    client.cancel(job)
    rc, out, err = run_cli(cli_bin, server.address, ["submit", str(folder)])
    assert rc == 0, err
    theirs_job = client.job(first_line(out))
    theirs = client._volumes.GetVolume(
        volumes_pb2.GetVolumeRequest(name=theirs_job.proto.spec.volume), timeout=10,
        metadata=client._metadata())
    client.cancel(theirs_job)
    assert ours.format == volumes_pb2.VOLUME_FORMAT_DICOM
    assert [(f.path, f.blob) for f in ours.files] == [(f.path, f.blob) for f in theirs.files]
    # Every slice, and neither the note, the DICOMDIR nor the folder's SHA256SUMS.
    assert sorted(f.path for f in ours.files) == sorted(
        n for n in os.listdir(series) if n.endswith(".dcm"))


def test_the_readme_notebook_example_runs_as_written(server, tmp_path, monkeypatch, capsys):
    readme = os.path.join(os.environ.get("DECIMA_PYCLIENT_SRC", ""), "README.md")
    if not os.path.isfile(readme):
        pytest.skip("DECIMA_PYCLIENT_SRC does not hold README.md (run through ctest)")
    with open(readme, encoding="utf-8") as f:
        text = f.read()
    code = text.split("## In a notebook", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert len(code.strip().splitlines()) <= 10
    # Only the address differs (a free port here); the token comes from DECIMA_TOKEN.
    assert code.count('"127.0.0.1:50051"') == 1
    code = code.replace('"127.0.0.1:50051"', f'"{server.address}"')
    monkeypatch.setenv("DECIMA_TOKEN", TOKEN)
    monkeypatch.chdir(tmp_path)
    nii = write_tiny_nifti(tmp_path / "tiny.nii", seed=15)
    with open(nii, "rb") as f, gzip.open(tmp_path / "ct-head.nii.gz", "wb") as out:
        out.write(f.read())
    exec(compile(code, "README.md", "exec"), {})
    printed = capsys.readouterr().out
    assert "100%" in printed and "mesh.vtu" in printed
    assert (tmp_path / "result" / "mesh.vtu").exists()
    assert (tmp_path / "result" / "labels.nii.gz").exists()
