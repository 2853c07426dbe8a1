#!/usr/bin/python3
"""PACS end-to-end test: real Orthanc (Debian orthanc + orthanc-dicomweb), real decima-server
with the C-STORE receiver, the real `decima` CLI. Loopback only; every process is started here
and stopped by its PID; every wait is bounded.

  A  receive: Orthanc C-STOREs the shared 113-slice CT series to a receiver whose quiet time is
     an hour (so no job); the instances are in the job store, also after a restart.
  B  a 113-slice copy of the CT head at 1/8 in-plane resolution (so the job takes seconds, not
     minutes, on a loaded 2-core machine), new UIDs, goes into Orthanc and then to Decima:
       (the receiver runs with the default quiet time)
       - one slice missing: no job; `decima series` shows it INCOMPLETE with the reason
         ("missing");
       - the missing slice follows: the series is complete, one job runs, created by the
         principal "dicom:ORTHANC";
       - the whole series again: the same SOP instance set, still one job;
       - `decima series` keeps the history: the receive that completed the series went up to
         SENT, the INCOMPLETE one before it became COMPLETE;
       - an unknown calling AE title: the association is refused;
       - the job's SEG, SC and Encapsulated STL models (one per region, dciodvfy-clean, in the
         source's frame of reference) come back into Orthanc (QIDO-RS) in the source study; the SEG
         passes dciodvfy without errors, and pydicom reads its segments back onto the source
         geometry with Dice 1.0 against the job's own label map (labels.nii.gz artifact: the
         shared data has no label map of this series);
     Another copy comes in as calling AE ORTHANC2, whose route sends the results by C-STORE.
  C  DICOMweb: `decima pull` of the 113-slice series (timed), `decima submit --dicomweb` of the
     small one runs as a job.
  D  abort: storescu --abort sends the first 60 slices of another copy (a contiguous run that
     looks whole): not queued; after a server restart still not queued (the abort mark is
     stored); the other 53 slices sent normally complete it and a job is queued.
Prints one JSON object of figures on the last line. Exit 77 (ctest: skipped) when a tool or the
shared data is missing.

usage: pacs_e2e_test.py DECIMA_SERVER_BIN DECIMA_CLI_BIN SHARED_DATA_DIR
"""
import gzip
import json
import os
import shutil
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
import base64

SKIP = 77
ORTHANC = "/usr/sbin/Orthanc"
DICOMWEB_PLUGIN = "/usr/share/orthanc/plugins/libOrthancDicomWeb.so"
USER, PASSWORD = "decima", "pacs-secret"


def skip(why):
    print(f"SKIPPED: {why}")
    sys.exit(SKIP)


def fail(why):
    print(f"FAILED: {why}")
    raise SystemExit(1)


def check(cond, why):
    if not cond:
        fail(why)


try:
    import numpy as np
    import pydicom
    from pydicom.uid import generate_uid
except ImportError as e:  # pragma: no cover
    skip(f"python3-pydicom / python3-numpy not installed ({e})")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Proc:
    """A child process with its log; stopped by PID."""

    def __init__(self, argv, log, env=None):
        self.log = log
        self.f = open(log, "wb")
        self.p = subprocess.Popen(argv, stdout=self.f, stderr=subprocess.STDOUT, env=env)

    def stop(self, timeout=15):
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        self.f.close()

    def text(self):
        with open(self.log, "rb") as f:
            return f.read().decode(errors="replace")


def wait_for(what, fn, timeout, period=0.05):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = fn()
        if v:
            return v
        time.sleep(period)
    fail(f"timed out after {timeout} s waiting for {what}")


class Orthanc:
    def __init__(self, tmp, decima_dicom_port):
        self.http = free_port()
        self.dicom = free_port()
        self.url = f"http://127.0.0.1:{self.http}"
        cfg = {
            "Name": "decima-e2e",
            "StorageDirectory": os.path.join(tmp, "orthanc-storage"),
            "IndexDirectory": os.path.join(tmp, "orthanc-index"),
            "HttpPort": self.http,
            "DicomPort": self.dicom,
            "DicomAet": "ORTHANC",
            "RemoteAccessAllowed": False,
            "AuthenticationEnabled": True,
            "RegisteredUsers": {USER: PASSWORD},
            "Plugins": [DICOMWEB_PLUGIN],
            "DicomWeb": {"Enable": True, "Root": "/dicom-web/"},
            "DicomModalities": {"decima": ["DECIMA", "127.0.0.1", decima_dicom_port]},
            "DicomAlwaysAllowStore": True,
            "DicomScuTimeout": 30,
            "StableAge": 3600,
            "HttpServerEnabled": True,
            "ConcurrentJobs": 1,
        }
        path = os.path.join(tmp, "orthanc.json")
        with open(path, "w") as f:
            json.dump(cfg, f)
        # Orthanc's DICOM layer is Debian's DCMTK too: without TCP_NODELAY=1 in its environment
        # its C-STORE to Decima waits on Nagle's algorithm (1.7 s instead of 0.2 s here).
        env = dict(os.environ, TCP_NODELAY="1")
        self.proc = Proc([ORTHANC, path], os.path.join(tmp, "orthanc.log"), env)
        wait_for("Orthanc", lambda: self.try_get("/system"), 60, 0.2)

    def request(self, method, path, body=None, ctype="application/json", accept=None):
        req = urllib.request.Request(self.url + path, method=method, data=body)
        auth = base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()
        req.add_header("Authorization", f"Basic {auth}")
        if body is not None:
            req.add_header("Content-Type", ctype)
        if accept:
            req.add_header("Accept", accept)
        with urllib.request.urlopen(req, timeout=120) as r:
            return r.read()

    def json(self, method, path, obj=None):
        body = None if obj is None else json.dumps(obj).encode()
        return json.loads(self.request(method, path, body))

    def try_get(self, path):
        try:
            return self.json("GET", path)
        except (urllib.error.URLError, ConnectionError, OSError):
            return None

    def upload(self, files):
        ids = []
        for f in files:
            with open(f, "rb") as fh:
                answer = self.request("POST", "/instances", fh.read(), "application/dicom")
                ids.append(json.loads(answer)["ID"])
        return ids

    def store_to_decima(self, resources, local_aet="ORTHANC"):
        """Orthanc C-STOREs `resources` to Decima; returns (ok, seconds, answer)."""
        t0 = time.monotonic()
        try:
            answer = self.json("POST", "/modalities/decima/store",
                               {"Resources": resources, "Synchronous": True,
                                "LocalAet": local_aet})
            return True, time.monotonic() - t0, answer
        except urllib.error.HTTPError as e:
            return False, time.monotonic() - t0, e.read().decode(errors="replace")


class Decima:
    def __init__(self, server_bin, cli_bin, tmp, name, dicom_port, quiet=None, routes=None):
        """quiet None: the server's default --dicom-quiet-seconds."""
        self.cli_bin = cli_bin
        self.data = os.path.join(tmp, f"{name}-data")
        self.port_file = os.path.join(tmp, f"{name}.port")
        self.dicom_port = dicom_port
        argv = [server_bin, "--listen", "127.0.0.1:0", "--port-file", self.port_file,
                "--data-dir", self.data, "--dicom-listen", f"127.0.0.1:{dicom_port}",
                "--dicom-aet", "DECIMA", "--dicom-min-free-mb", "64",
                "--heartbeat-seconds", "0.5"]
        if quiet is not None:
            argv += ["--dicom-quiet-seconds", str(quiet)]
        if routes:
            argv += ["--dicom-routes", routes]
        if os.path.exists(self.port_file):
            os.remove(self.port_file)
        self.proc = Proc(argv, os.path.join(tmp, f"{name}.log"))
        port = wait_for("decima-server port file",
                        lambda: os.path.exists(self.port_file) and open(self.port_file).read().strip(),
                        60, 0.05)
        self.server = f"127.0.0.1:{port}"

    def cli(self, *args, timeout=300):
        r = subprocess.run([self.cli_bin, "--server", self.server, "--json", "--quiet", *args],
                           capture_output=True, text=True, timeout=timeout)
        return r

    def jobs(self):
        r = self.cli("list", "--all")
        check(r.returncode == 0, f"decima list: {r.stderr}")
        return [json.loads(line) for line in r.stdout.splitlines() if line.strip()]

    def series(self, uid=None):
        """`decima series -o json`: the received series (only `uid`'s when given)."""
        r = self.cli("series", "--all")
        check(r.returncode == 0, f"decima series: {r.stderr}")
        rows = [json.loads(line) for line in r.stdout.splitlines() if line.strip()]
        return [x for x in rows if uid is None or x["series_instance_uid"] == uid]

    def db(self, sql):
        con = sqlite3.connect(f"file:{os.path.join(self.data, 'jobs.sqlite')}?mode=ro", uri=True,
                              timeout=10)
        try:
            return con.execute(sql).fetchall()
        finally:
            con.close()


def sort_along_normal(datasets):
    iop = [float(v) for v in datasets[0].ImageOrientationPatient]
    n = np.cross(iop[:3], iop[3:])
    return sorted(datasets, key=lambda d: float(np.dot(n, [float(v) for v in d.ImagePositionPatient])))


def make_small_series(src_dir, out_dir, block):
    """The shared CT at 1/block in-plane resolution: 113 slices, new study/series/SOP UIDs."""
    os.makedirs(out_dir)
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    files = sorted(f for f in os.listdir(src_dir) if f.endswith(".dcm"))
    out = []
    for name in files:
        ds = pydicom.dcmread(os.path.join(src_dir, name))
        px = ds.pixel_array.astype(np.float64)
        r, c = px.shape
        small = px.reshape(r // block, block, c // block, block).mean(axis=(1, 3))
        small = np.rint(small).astype(np.uint16)
        row_dir = np.array([float(v) for v in ds.ImageOrientationPatient[:3]])
        col_dir = np.array([float(v) for v in ds.ImageOrientationPatient[3:]])
        dr, dc = (float(v) for v in ds.PixelSpacing)  # between rows, between columns
        ipp = np.array([float(v) for v in ds.ImagePositionPatient])
        # The centre of the first block: (block-1)/2 pixels along both in-plane axes.
        ipp = ipp + (block - 1) / 2 * (dc * row_dir + dr * col_dir)
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.Rows, ds.Columns = small.shape
        ds.PixelSpacing = [f"{dr * block:g}", f"{dc * block:g}"]
        ds.ImagePositionPatient = [f"{v:.4f}" for v in ipp]
        ds.PixelData = small.tobytes()
        ds.SeriesDescription = f"CT head 1/{block}"
        path = os.path.join(out_dir, name)
        ds.save_as(path)
        out.append(path)
    return out, study, series


def read_nifti(path):
    with gzip.open(path, "rb") as f:
        raw = f.read()
    dims = struct.unpack("<8h", raw[40:56])
    datatype = struct.unpack("<h", raw[70:72])[0]
    offset = int(struct.unpack("<f", raw[108:112])[0])
    check(datatype == 2, f"{path}: labels are datatype {datatype}, expected uint8 (2)")
    nx, ny, nz = dims[1], dims[2], dims[3]
    return np.frombuffer(raw[offset:offset + nx * ny * nz], np.uint8).reshape(nz, ny, nx)


def seg_dice(seg_path, source_files, labels, regions):
    """Rebuilds the label volume from the SEG on the source geometry; Dice per region the job's
    region table (metrics.json "regions") keeps in the SEG, matched by segment label = name."""
    seg = pydicom.dcmread(seg_path)
    check(seg.SOPClassUID == "1.2.840.10008.5.1.4.1.1.66.4", "not a SEG")
    check(seg.SegmentationType == "BINARY", f"SegmentationType {seg.SegmentationType}")
    sources = sort_along_normal([pydicom.dcmread(f, stop_before_pixels=True) for f in source_files])
    slice_of = {d.SOPInstanceUID: k for k, d in enumerate(sources)}
    refs = seg.ReferencedSeriesSequence
    check(len(refs) == 1 and refs[0].SeriesInstanceUID == sources[0].SeriesInstanceUID,
          "ReferencedSeriesSequence does not name the source series")
    check(len(refs[0].ReferencedInstanceSequence) == len(sources),
          f"ReferencedInstanceSequence has {len(refs[0].ReferencedInstanceSequence)} items")
    check(seg.StudyInstanceUID == sources[0].StudyInstanceUID, "SEG not in the source study")
    check(seg.FrameOfReferenceUID == sources[0].FrameOfReferenceUID, "SEG frame of reference")
    rows, cols, n = seg.Rows, seg.Columns, int(seg.NumberOfFrames)
    check((rows, cols) == (sources[0].Rows, sources[0].Columns), "SEG frame size")
    bits = np.unpackbits(np.frombuffer(seg.PixelData, np.uint8), bitorder="little")
    frames = bits[: n * rows * cols].reshape(n, rows, cols)
    label_of_name = {r["name"]: r["label"] for r in regions if r["dicom_seg"]}
    label_of_segment = {}
    for s in seg.SegmentSequence:
        check(s.SegmentLabel in label_of_name, f"segment label {s.SegmentLabel} not a SEG region")
        label_of_segment[int(s.SegmentNumber)] = label_of_name[s.SegmentLabel]
        check(len(s.SegmentedPropertyCategoryCodeSequence) == 1, "category code")
        check(len(s.SegmentedPropertyTypeCodeSequence) == 1, "type code")
    rebuilt = np.full(labels.shape, 255, np.uint8)
    for i, fg in enumerate(seg.PerFrameFunctionalGroupsSequence):
        number = int(fg.SegmentIdentificationSequence[0].ReferencedSegmentNumber)
        uid = fg.DerivationImageSequence[0].SourceImageSequence[0].ReferencedSOPInstanceUID
        k = slice_of[uid]
        pos = [float(v) for v in fg.PlanePositionSequence[0].ImagePositionPatient]
        check(np.allclose(pos, [float(v) for v in sources[k].ImagePositionPatient], atol=1e-3),
              f"frame {i + 1}: plane position differs from its source slice")
        mask = frames[i].astype(bool)
        check(not (rebuilt[k][mask] != 255).any(), f"frame {i + 1}: segments overlap")
        rebuilt[k][mask] = label_of_segment[number]
    dice = {}
    for r in sorted(set(np.unique(labels).tolist()) & set(label_of_segment.values())):
        a, b = labels == r, rebuilt == r
        dice[regions[r]["name"]] = float(2 * np.logical_and(a, b).sum() / (a.sum() + b.sum()))
    return dice, len(seg.SegmentSequence), n


def dciodvfy_errors(path):
    r = subprocess.run(["dciodvfy", path], capture_output=True, text=True, timeout=120)
    out = r.stdout + r.stderr
    return [l for l in out.splitlines() if l.startswith("Error")], out


def main():
    if len(sys.argv) != 4:
        fail(__doc__)
    server_bin, cli_bin, shared = sys.argv[1:4]
    series_dir = os.path.join(shared, "ct-head-256x256x113-dicom")
    if not os.path.isdir(series_dir):
        skip(f"{series_dir} absent (the shared data is not on this machine)")
    for tool in (ORTHANC, DICOMWEB_PLUGIN, shutil.which("dciodvfy") or "/nonexistent/dciodvfy"):
        if not os.path.exists(tool):
            skip(f"{tool} not installed (Debian orthanc, orthanc-dicomweb, dicom3tools)")
    figures = {}
    tmp = tempfile.mkdtemp(prefix="decima-pacs-e2e-")
    procs = []
    try:
        real_files = sorted(os.path.join(series_dir, f) for f in os.listdir(series_dir)
                            if f.endswith(".dcm"))
        check(len(real_files) == 113, f"{len(real_files)} files in {series_dir}")
        dicom_port = free_port()
        orthanc = Orthanc(tmp, dicom_port)
        procs.append(orthanc.proc)

        # --- A: receive the real 113-slice series (an hour of quiet: no job) -----------------
        a = Decima(server_bin, cli_bin, tmp, "a", dicom_port, 3600)
        procs.append(a.proc)
        ids = orthanc.upload(real_files)
        real_series = orthanc.json("GET", f"/instances/{ids[0]}")["ParentSeries"]
        real_study_uid = pydicom.dcmread(real_files[0], stop_before_pixels=True).StudyInstanceUID
        real_series_uid = pydicom.dcmread(real_files[0], stop_before_pixels=True).SeriesInstanceUID
        times = []
        for _ in range(3):  # the same set each time: replaced rows, still 113
            ok, secs, answer = orthanc.store_to_decima([real_series])
            check(ok, f"Orthanc -> Decima C-STORE failed: {answer}")
            times.append(secs)
        figures["receive_113_slices_seconds"] = sorted(times)[1]
        figures["receive_113_slices_runs"] = [round(t, 4) for t in times]
        check(a.db("SELECT COUNT(*) FROM dicom_instances")[0][0] == 113, "113 instances stored")
        a.proc.stop()
        procs.remove(a.proc)
        a = Decima(server_bin, cli_bin, tmp, "a", dicom_port, 3600)  # restart: state survives
        procs.append(a.proc)
        check(a.db("SELECT COUNT(*) FROM dicom_instances")[0][0] == 113,
              "instances lost over a restart")
        check(a.jobs() == [], "a job was queued before the quiet time ended")
        a.proc.stop()
        procs.remove(a.proc)

        # --- B: the small copy through the whole loop ------------------------------------------
        small_files, study_uid, series_uid = make_small_series(series_dir,
                                                               os.path.join(tmp, "small"), 8)
        routes = os.path.join(tmp, "routes.json")
        spec = {"regions": 3, "targetReduction": 0.3, "policy": "PAPER", "imageSize": 64,
                "views": ["anterior"]}
        with open(routes, "w") as f:
            json.dump({"refuse_unknown_calling_ae": True,
                       "routes": [{"name": "orthanc", "calling_ae": "ORTHANC",
                                   "called_ae": "DECIMA", "spec": spec,
                                   "destination": {"stow_url": f"{orthanc.url}/dicom-web/studies",
                                                   "username": USER, "password": PASSWORD}},
                                  {"name": "orthanc-cstore", "calling_ae": "ORTHANC2",
                                   "called_ae": "DECIMA", "spec": spec,
                                   "destination": {"dicom": f"127.0.0.1:{orthanc.dicom}",
                                                   "aet": "ORTHANC"}}]}, f)
        b = Decima(server_bin, cli_bin, tmp, "b", dicom_port, None, routes)  # default quiet time
        procs.append(b.proc)
        started = wait_for("the receiver's start line",
                           lambda: [l for l in b.proc.text().splitlines() if "(quiet " in l], 30)
        quiet = float(started[0].split("(quiet ")[1].split(" s")[0])
        small_ids = orthanc.upload(small_files)
        missing = small_ids[56]
        ok, _, answer = orthanc.store_to_decima([i for i in small_ids if i != missing])
        check(ok, f"C-STORE of 112 slices failed: {answer}")
        # The reason through the API (decima series), not only the log and the job store.
        listed = wait_for("the series listed INCOMPLETE", lambda: [
            x for x in b.series(series_uid) if x.get("state") == "INCOMPLETE"], 30, 0.1)[0]
        check("missing" in listed.get("reason", ""),
              f"reason does not say a slice is missing: {listed}")
        check(listed["instance_count"] == 112 and listed["calling_ae"] == "ORTHANC"
              and listed["called_ae"] == "DECIMA" and listed["owner"] == "dicom:ORTHANC",
              f"listed series: {listed}")
        check(b.jobs() == [], "an incomplete series queued a job")
        figures["incomplete_reason"] = listed["reason"]
        table = subprocess.run([cli_bin, "--server", b.server, "series"], capture_output=True,
                               text=True, timeout=60)
        check(table.returncode == 0 and table.stdout.startswith("SERIES") and
              "INCOMPLETE" in table.stdout, f"decima series table: {table.stdout} {table.stderr}")

        ok, _, answer = orthanc.store_to_decima([missing], local_aet="STRANGER")
        check(not ok, "an unknown calling AE title was accepted")
        check("no route for calling AE title 'STRANGER'" in b.proc.text(), "refusal not logged")

        t_send = time.monotonic()
        ok, _, answer = orthanc.store_to_decima([missing])  # completes the series
        check(ok, f"C-STORE of the missing slice failed: {answer}")
        job = wait_for("one job", lambda: b.jobs(), 30)
        check(len(job) == 1, f"{len(job)} jobs")
        job_name = job[0]["name"]
        check(job[0].get("creator") == "dicom:ORTHANC", f"job creator: {job[0].get('creator')}")
        final = wait_for("the job to end", lambda: [j for j in b.jobs()
                                                     if j["state"] in ("SUCCEEDED", "FAILED",
                                                                       "CANCELLED")], 600, 0.2)[0]
        check(final["state"] == "SUCCEEDED", f"job ended {final['state']}: {final.get('error')}")

        def qido_series():
            answer = orthanc.request("GET", f"/dicom-web/studies/{study_uid}/series",
                                     accept="application/dicom+json")
            mods = [s["00080060"]["Value"][0] for s in json.loads(answer)]
            return mods if "SEG" in mods and "OT" in mods and "M3D" in mods else None

        mods = wait_for("SEG, SC and STL models in Orthanc", qido_series, 120, 0.05)
        t_back = time.monotonic() - t_send
        start = final["start_time"], final["end_time"]

        def ts(s):
            s = s.rstrip("Z")
            main_part, _, frac = s.partition(".")
            return time.mktime(time.strptime(main_part, "%Y-%m-%dT%H:%M:%S")) + float("0." + (frac or "0"))

        job_seconds = ts(start[1]) - ts(start[0])
        figures["orthanc_to_seg_sc_in_orthanc_seconds"] = round(t_back, 3)
        figures["job_seconds"] = round(job_seconds, 3)
        figures["overhead_seconds"] = round(t_back - job_seconds, 3)
        figures["quiet_seconds"] = quiet
        check(mods.count("CT") == 1, f"series in the study: {mods}")
        # The history: the receive that completed it went up to SENT, the INCOMPLETE one before
        # it is COMPLETE with the same job.
        queued = wait_for("the receive SENT", lambda: [
            x for x in b.series(series_uid) if x.get("state") == "SENT"] and b.series(series_uid),
            30, 0.1)
        check(len(queued) == 2 and queued[0]["state"] == "SENT" and queued[0]["job"] == job_name
              and queued[0]["instance_count"] == 113 and queued[1]["state"] == "COMPLETE"
              and queued[1]["job"] == job_name and queued[1]["instance_count"] == 112,
              f"listed after the job: {queued}")

        # The whole series again: same SOP instance set, no second job.
        all_small_series = orthanc.json("GET", f"/instances/{small_ids[0]}")["ParentSeries"]
        ok, _, answer = orthanc.store_to_decima([all_small_series])
        check(ok, f"re-send failed: {answer}")
        wait_for("the re-sent series to be settled",
                 lambda: "re-sent" in b.proc.text(), quiet + 30, 0.1)
        check(len(b.jobs()) == 1, "the re-sent series made a second job")

        # SEG: dciodvfy and pydicom against the job's own label map.
        found = orthanc.json("POST", "/tools/find", {"Level": "Instance", "Expand": True,
                                                     "Query": {"StudyInstanceUID": study_uid,
                                                               "Modality": "SEG"}})
        check(len(found) == 1, f"{len(found)} SEG instances in Orthanc")
        seg_path = os.path.join(tmp, "seg.dcm")
        with open(seg_path, "wb") as f:
            f.write(orthanc.request("GET", f"/instances/{found[0]['ID']}/file"))
        errors, report = dciodvfy_errors(seg_path)
        check(not errors, "dciodvfy errors:\n" + "\n".join(errors))
        figures["dciodvfy_seg_errors"] = len(errors)
        figures["dciodvfy_seg_warnings"] = sum(1 for l in report.splitlines()
                                               if l.startswith("Warning"))
        job_id = job_name.split("/")[1]
        # The job's own label map, fetched as any client would (not read from the data dir).
        fetched = os.path.join(tmp, "fetched")
        r = b.cli("fetch", job_id, "--out", fetched, "--only", "labels.nii.gz", "metrics.json")
        check(r.returncode == 0, f"decima fetch labels.nii.gz metrics.json: {r.stderr}")
        labels = read_nifti(os.path.join(fetched, "labels.nii.gz"))
        with open(os.path.join(fetched, "metrics.json")) as f:
            regions = json.load(f)["regions"]
        dice, segments, frames = seg_dice(seg_path, small_files, labels, regions)
        check(all(v == 1.0 for v in dice.values()), f"Dice {dice}")
        figures["seg_dice"] = dice
        figures["seg_segments"], figures["seg_frames"] = segments, frames
        sc = orthanc.json("POST", "/tools/find", {"Level": "Instance", "Expand": True,
                                                  "Query": {"StudyInstanceUID": study_uid,
                                                            "Modality": "OT"}})
        check(len(sc) == 2, f"{len(sc)} SC instances (comparison and diff expected)")
        sc_path = os.path.join(tmp, "sc.dcm")
        with open(sc_path, "wb") as f:
            f.write(orthanc.request("GET", f"/instances/{sc[0]['ID']}/file"))
        sc_errors, _ = dciodvfy_errors(sc_path)
        figures["dciodvfy_sc_errors"] = len(sc_errors)
        check(not sc_errors, "dciodvfy errors on SC:\n" + "\n".join(sc_errors))
        sent = b.db(f"SELECT send_status FROM dicom_series WHERE job='{job_name}'")
        # The region surfaces: one Encapsulated STL per region (air too, which the SEG leaves
        # out), named, dciodvfy-clean.
        models = orthanc.json("POST", "/tools/find", {"Level": "Instance", "Expand": True,
                                                      "Query": {"StudyInstanceUID": study_uid,
                                                                "Modality": "M3D"}})
        check(len(models) == spec["regions"],
              f"{len(models)} STL models for {spec['regions']} regions")
        model_path = os.path.join(tmp, "model.dcm")
        with open(model_path, "wb") as f:
            f.write(orthanc.request("GET", f"/instances/{models[0]['ID']}/file"))
        model_errors, _ = dciodvfy_errors(model_path)
        figures["stl_models"] = len(models)
        figures["dciodvfy_stl_errors"] = len(model_errors)
        check(not model_errors, "dciodvfy errors on the STL model:\n" + "\n".join(model_errors))
        stl = pydicom.dcmread(model_path)
        check(stl.SOPClassUID == "1.2.840.10008.5.1.4.1.1.104.3"
              and stl.MIMETypeOfEncapsulatedDocument == "model/stl"
              and stl.FrameOfReferenceUID == pydicom.dcmread(small_files[0]).FrameOfReferenceUID
              and len(stl.EncapsulatedDocument) >= stl.EncapsulatedDocumentLength > 84,
              f"STL model: {stl.SOPClassUID} {stl.MIMETypeOfEncapsulatedDocument}")
        sent_count = 3 + len(models)
        check([r for r in sent
               if r[0].startswith(f"sent: {sent_count} instances stored by STOW-RS")], f"{sent}")

        # Results by C-STORE: another copy (new UIDs) through the route of calling AE ORTHANC2.
        files2, study2, _ = make_small_series(series_dir, os.path.join(tmp, "small2"), 8)
        ids2 = orthanc.upload(files2)
        ok, _, answer = orthanc.store_to_decima(
            [orthanc.json("GET", f"/instances/{ids2[0]}")["ParentSeries"]], local_aet="ORTHANC2")
        check(ok, f"C-STORE as ORTHANC2 failed: {answer}")
        wait_for("the C-STORE route's job", lambda: len(b.jobs()) == 2, 30, 0.1)
        job2 = [j["name"] for j in b.jobs() if j["name"] != job_name][0]
        sent2 = wait_for("results sent by C-STORE", lambda: [
            r for r in b.db(f"SELECT send_status FROM dicom_series WHERE job='{job2}'")
            if r[0]], 600, 0.2)
        check(sent2[0][0].startswith(f"sent: {sent_count} instances stored by C-STORE at ORTHANC@"),
              f"C-STORE send: {sent2}")
        mods2 = json.loads(orthanc.request("GET", f"/dicom-web/studies/{study2}/series",
                                           accept="application/dicom+json"))
        mods2 = sorted(x["00080060"]["Value"][0] for x in mods2)
        check(mods2 == ["CT", "M3D", "OT", "SEG"], f"series after C-STORE: {mods2}")

        # --- C: DICOMweb pull ---------------------------------------------------------------------
        base = f"{orthanc.url}/dicom-web"
        pulls = []
        for i in range(3):
            out = os.path.join(tmp, f"pulled-{i}")
            r = b.cli("pull", "--dicomweb", base, "--study", real_study_uid, "--series",
                      real_series_uid, "--dicomweb-user", f"{USER}:{PASSWORD}", "--out", out)
            check(r.returncode == 0, f"decima pull: {r.stderr}")
            got = json.loads(r.stdout)
            check(got["instances"] == 113, f"pulled {got['instances']} instances")
            pulls.append(got["seconds"])
        figures["wado_rs_pull_113_seconds"] = sorted(pulls)[1]
        figures["wado_rs_pull_113_runs"] = pulls
        r = b.cli("pull", "--dicomweb", base, "--study", real_study_uid,
                  "--out", os.path.join(tmp, "unauth"))
        check(r.returncode != 0 and "401" in r.stderr, f"pull without credentials: {r.stderr}")
        r = b.cli("submit", "--dicomweb", base, "--study", study_uid, "--series", series_uid,
                  "--dicomweb-user", f"{USER}:{PASSWORD}", "--regions", "2", "--image-size", "32",
                  "--policy", "paper", "--reduction", "0.2", "--watch", timeout=600)
        check(r.returncode == 0, f"decima submit --dicomweb: {r.returncode} {r.stderr[-500:]}")
        check(len(b.jobs()) == 3, "the DICOMweb job is not there")

        # --- D: an aborted association, a restart, then the rest -------------------------------
        files3, _, series3 = make_small_series(series_dir, os.path.join(tmp, "small3"), 8)

        def storescu(files, abort):
            argv = ["storescu", "-aet", "ORTHANC", "-aec", "DECIMA", "127.0.0.1", str(dicom_port)]
            return subprocess.run(argv + (["--abort"] if abort else []) + files,
                                  capture_output=True, text=True, timeout=120)

        r = storescu(files3[:60], True)
        aborted = wait_for("the aborted series listed", lambda: [
            x for x in b.series(series3) if x.get("state") == "INCOMPLETE"], 30, 0.1)[0]
        check("aborted" in aborted["reason"] and aborted["instance_count"] == 60,
              f"after the abort: {aborted} (storescu: {r.stderr[-300:]})")
        b.proc.stop()
        procs.remove(b.proc)
        b = Decima(server_bin, cli_bin, tmp, "b", dicom_port, None, routes)  # restart
        procs.append(b.proc)
        wait_for("the restarted receiver to check the aborted series",
                 lambda: f"series {series3} (60 instances from ORTHANC) not queued: the "
                         "association that sent it was aborted" in b.proc.text(), quiet + 30, 0.1)
        check(len(b.jobs()) == 3, "the aborted series was queued after a restart")
        still = b.series(series3)
        check(len(still) == 1 and still[0]["state"] == "INCOMPLETE", f"after the restart: {still}")
        r = storescu(files3[60:], False)
        check(r.returncode == 0, f"storescu of the other 53 slices: {r.stderr[-500:]}")
        wait_for("the completed series' job", lambda: len(b.jobs()) == 4, quiet + 30, 0.1)
        done = b.series(series3)
        check(len(done) == 2 and done[0]["state"] in ("QUEUED", "RUNNING", "SUCCEEDED", "SENT")
              and done[0]["instance_count"] == 113 and done[1]["state"] == "COMPLETE",
              f"after the rest: {done}")
        job3 = [j for j in b.jobs() if j["name"] == done[0]["job"]]
        check(job3 and job3[0].get("creator") == "dicom:ORTHANC", f"job of the rest: {job3}")
        print(json.dumps(figures))
    finally:
        for p in reversed(procs):
            p.stop()
        if os.environ.get("DECIMA_KEEP_TMP"):
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
