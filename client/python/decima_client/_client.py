"""Client and Job: the `decima` CLI's submit, watch, fetch, list, cancel, delete and series as
Python calls, with the CLI's semantics (client/cmd/, client/cli/, client/client_lib.cc):

- Before the first call the client waits at most min(5 s, timeout) for the connection and
  raises ServerUnreachable when the address refuses it or nothing answers. Only a server that
  answered once is retried: unary calls are retried on UNAVAILABLE (a restart) for up to
  `reconnect` seconds.
- Every call has a deadline: unary calls `timeout`; an upload or a download `timeout` plus its
  bytes at 256 KiB/s; each WatchJob stream `timeout`, after which the watch resumes from the
  last sequence it saw (the server sends a heartbeat every few seconds, so a stream that brings
  nothing at all in that time means the server hangs, and the watch raises DeadlineExceeded).
- watch() reconnects with the last sequence it saw when the server goes away (UNAVAILABLE, or a
  stream the server's shutdown cut), for up to `reconnect` seconds, and so misses no event.
"""
import hashlib
import json
import logging
import math
import os
import queue
import socket
import time
import uuid

import grpc

from . import _header
from . import _inputs
from . import errors
from .proto import artifacts_pb2, artifacts_pb2_grpc, jobs_pb2, jobs_pb2_grpc
from .proto import uploads_pb2, uploads_pb2_grpc, volumes_pb2, volumes_pb2_grpc

log = logging.getLogger("decima_client")

DEFAULT_SERVER = "127.0.0.1:50051"
_CHUNK = 1 << 20  # the server's largest upload message
# The slowest transfer a stream's deadline allows for (bytes per second), on top of `timeout`.
_MIN_RATE = 256 * 1024
_MAX_PAGES = 1000  # bounds every listing loop (a million entries at 1000 per page)

_POLICIES = {"paper": jobs_pb2.PAPER, "tetfusion": jobs_pb2.TETFUSION, "field": jobs_pb2.FIELD}
_WEIGHTS = {"w_r": "regional", "regional": "regional", "w_g": "gradient", "gradient": "gradient",
            "w_s": "shape", "shape": "shape", "w_v": "volume", "volume": "volume",
            "w_n": "neighbour", "neighbour": "neighbour"}
# submit() keywords: the JobSpec field each sets (the CLI's flag names are accepted too).
_SPEC_KEYS = {"regions": "regions", "class_means": "class_means", "region_names": "region_names",
              "target_reduction": "target_reduction", "reduction": "target_reduction",
              "error_tolerance": "error_tolerance", "tolerance": "error_tolerance",
              "policy": "policy", "weights": "weights", "views": "views",
              "image_size": "image_size", "transfer_function": "transfer_function",
              "outputs": "outputs", "vtu_compression_level": "vtu_compression_level",
              "vtu_level": "vtu_compression_level", "min_psnr": "min_psnr",
              "interfaces": "interfaces", "mesh_compression": "mesh_compression",
              "stream_slab_voxels": "stream_slab_voxels"}
# fetch(outputs=...) kinds, as the CLI's --only: kind -> file name.
_KIND_FILES = {"vtu": "mesh.vtu", "msh": "mesh.msh", "medit": "mesh.mesh", "levels": "mesh.levels",
               "labels": "labels.nii.gz", "segmentation": "segmentation.png",
               "report": "report.html", "curve": "curve.png", "metrics": "metrics.json"}
_FINAL = (jobs_pb2.SUCCEEDED, jobs_pb2.FAILED, jobs_pb2.CANCELLED)
# Each stage's share of a job, in seconds of the CT head job (field policy, 50 %, one 512 px
# view): the CLI's weights (client/client_lib.cc kStageWeights, client/README.md), kept equal so
# that a notebook's bar and `decima watch` agree. "curve" counts only for jobs that asked for it.
_STAGE_WEIGHTS = (("load", 0.03), ("segment", 2.24), ("tetra", 1.74), ("simplify", 14.8),
                  ("write", 0.85), ("render", 7.16), ("curve", 41.4), ("diff", 0.05))


# The kinds a level job can write (its mesh comes from a record, so no "levels" or "curve").
_LEVEL_KINDS = ("vtu", "msh", "medit", "stl", "glb", "labels", "images", "segmentation", "report")


def overall_fraction(progress, with_curve=False):
    """A job's overall progress, 0..1, from a decima.v1.Progress: the job's own figure
    (overall_fraction, from its stage model and measured rates) when the event carries it, else
    the stage and the fraction within it weighted as the CLI's bar does; 0 for an unknown
    stage."""
    if progress.HasField("overall_fraction"):
        return min(max(progress.overall_fraction, 0.0), 1.0)
    total = before = own = 0.0
    found = False
    for stage, seconds in _STAGE_WEIGHTS:
        if stage == "curve" and not with_curve:
            continue
        if stage == progress.stage:
            found, own = True, seconds
        elif not found:
            before += seconds
        total += seconds
    if not found:
        return 0.0
    return min(max((before + own * min(max(progress.fraction, 0.0), 1.0)) / total, 0.0), 1.0)


def _duration(seconds):
    """"0:05", "1:02:03", as the CLI's FormatDuration."""
    s = int(seconds + 0.5)
    if s >= 3600:
        return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
    return f"{s // 60}:{s % 60:02d}"


def _matches(file_name, only):
    """Whether an artifact file is selected by `only` (file names or kinds; empty: all)."""
    if not only:
        return True
    for o in only:
        o = o.lower()
        if o == file_name or _KIND_FILES.get(o) == file_name:
            return True
        if (o == "images" and file_name.endswith(".png")
                and file_name not in ("segmentation.png", "curve.png")):
            return True
    return False


def _names(value, what):
    """A list of names from a list or a comma-separated string."""
    if value is None:
        return []
    if isinstance(value, str):
        return [v for v in value.split(",") if v]
    try:
        return [str(v) for v in value]
    except TypeError:
        raise errors.InputError(f"{what}={value!r}: expected a list of names or a "
                                "comma-separated string") from None


def _views(value):
    """Views as the CLI takes them: "30,20" alone is the custom view 30:20, never two views."""
    raw = _names(value, "views")

    def number(s):
        try:
            float(s)
            return True
        except ValueError:
            return False

    out, i = [], 0
    while i < len(raw):
        if number(raw[i]) and i + 1 < len(raw) and number(raw[i + 1]):
            out.append(raw[i] + ":" + raw[i + 1])
            i += 2
        else:
            out.append(raw[i])
            i += 1
    return out


class Client:
    """A connection to decima-server.

    address: "host:port" (default $DECIMA_SERVER, else 127.0.0.1:50051).
    token: the bearer token (default $DECIMA_TOKEN).
    tls: False for plaintext, True for TLS with the system's roots; ca_cert (PEM roots, default
      $DECIMA_CA_CERT), and cert + key (a client certificate for mutual TLS, default
      $DECIMA_TLS_CERT and $DECIMA_TLS_KEY) imply TLS.
    timeout: deadline of each call, seconds (default $DECIMA_TIMEOUT, else 30).
    reconnect: how long a call or a watch keeps retrying a server that went away, seconds.
    """

    def __init__(self, address=None, token=None, tls=False, *, ca_cert=None, cert=None,
                 key=None, timeout=None, reconnect=60.0):
        env_server = os.environ.get("DECIMA_SERVER")
        if address:
            self._source = "from Client(address)"
        elif env_server:
            self._source = "from DECIMA_SERVER"
        else:
            self._source = "the default"
        self.address = address or env_server or DEFAULT_SERVER
        self.token = token if token is not None else os.environ.get("DECIMA_TOKEN", "")
        if timeout is None:
            try:
                timeout = float(os.environ.get("DECIMA_TIMEOUT", "30"))
            except ValueError:
                raise errors.InputError(
                    f"DECIMA_TIMEOUT={os.environ['DECIMA_TIMEOUT']!r}: expected seconds") from None
        if not timeout > 0:
            raise errors.InputError(f"timeout={timeout!r}: expected seconds > 0")
        self.timeout = float(timeout)
        self.reconnect = float(reconnect)
        # The CLI's environment defaults of --ca-cert, --tls-cert and --tls-key.
        ca_cert = ca_cert or os.environ.get("DECIMA_CA_CERT") or None
        cert = cert or os.environ.get("DECIMA_TLS_CERT") or None
        key = key or os.environ.get("DECIMA_TLS_KEY") or None
        self._tls = bool(tls or ca_cert or cert or key)
        options = [("grpc.max_receive_message_length", 8 << 20)]
        if self._tls:
            if bool(cert) != bool(key):
                raise errors.InputError("cert and key go together (a client certificate and its "
                                        "key)")

            def read(flag, path):
                try:
                    with open(path, "rb") as f:
                        return f.read()
                except OSError:
                    raise errors.InputError(f"{flag} {path}: cannot read") from None

            creds = grpc.ssl_channel_credentials(
                root_certificates=read("ca_cert", ca_cert) if ca_cert else None,
                private_key=read("key", key) if key else None,
                certificate_chain=read("cert", cert) if cert else None)
            self._channel = grpc.secure_channel(self.address, creds, options=options)
        else:
            self._channel = grpc.insecure_channel(self.address, options=options)
        self._jobs = jobs_pb2_grpc.JobsStub(self._channel)
        self._volumes = volumes_pb2_grpc.VolumesStub(self._channel)
        self._uploads = uploads_pb2_grpc.UploadsStub(self._channel)
        self._artifacts = artifacts_pb2_grpc.ArtifactsStub(self._channel)
        # Set after the first answer: from then on UNAVAILABLE means "restarting" and is
        # retried; before it the address is probably wrong and calls fail at once.
        self._ever_connected = False
        # Extra metadata of CreateJob: the tests' fault seam ("decima-test-fault"), which only a
        # server started with --allow-faults reads (as the CLI's hidden --fault flag).
        self._create_job_metadata = ()

    def close(self):
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- plumbing -------------------------------------------------------------------------

    def _metadata(self):
        return (("authorization", "Bearer " + self.token),) if self.token else ()

    def _tcp_answers(self, seconds=1.0):
        """Whether something accepts TCP connections at the address (as the CLI checks)."""
        host, _, port = self.address.rpartition(":")
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=seconds):
                return True
        except (OSError, ValueError):
            return False

    def _unreachable(self, what, detail):
        # Something accepts TCP there, so the server may well run: a plaintext call to a TLS
        # server fails exactly like this. Same words as the CLI's.
        if not self._tls and self._tcp_answers():
            return errors.ServerUnreachable(
                f"{what}: cannot talk to decima-server at {self.address} ({self._source}): "
                f"{detail}\n  hint: something accepts connections there, so the server may "
                "serve TLS (decima-server --tls-cert): pass tls=True, with ca_cert=CA.pem for "
                "a private CA (or DECIMA_CA_CERT)", what=what, server_message=detail,
                code=grpc.StatusCode.UNAVAILABLE)
        hint = ("\n  hint: is the server running there? Start it with `decima-server --listen "
                f"{self.address}`, or pass its address to Client() or set DECIMA_SERVER.")
        if self._tls:
            hint += ("\n  over TLS this is also what a refused handshake looks like: check "
                     "ca_cert (the server's CA), and under mutual TLS cert/key (a client "
                     "certificate the server's --tls-client-ca signed)")
        return errors.ServerUnreachable(
            f"{what}: cannot reach decima-server at {self.address} ({self._source}): "
            f"{detail}{hint}", what=what, server_message=detail,
            code=grpc.StatusCode.UNAVAILABLE)

    def _ensure_reachable(self, what):
        """Waits at most min(5 s, timeout) for the connection; raises ServerUnreachable when
        it is refused or nothing answers (instead of retrying for a minute)."""
        if self._ever_connected:
            return
        limit = min(5.0, self.timeout)
        states = queue.Queue()
        self._channel.subscribe(states.put, try_to_connect=True)
        try:
            deadline = time.monotonic() + limit
            while True:
                remaining = deadline - time.monotonic()
                try:
                    if remaining <= 0:
                        raise queue.Empty
                    state = states.get(timeout=remaining)
                except queue.Empty:
                    raise self._unreachable(what, f"no answer within {_duration(limit)}") from None
                if state == grpc.ChannelConnectivity.READY:
                    break
                if state in (grpc.ChannelConnectivity.TRANSIENT_FAILURE,
                             grpc.ChannelConnectivity.SHUTDOWN):
                    raise self._unreachable(what, "connection refused or failed")
        finally:
            self._channel.unsubscribe(states.put)
        self._ever_connected = True

    def _error(self, e, what):
        """The typed error of a failed call, worded as the CLI's Report()."""
        code = e.code() if callable(getattr(e, "code", None)) else None
        if not self._ever_connected and code in (grpc.StatusCode.UNAVAILABLE,
                                                 grpc.StatusCode.DEADLINE_EXCEEDED):
            return self._unreachable(what, f"{code.name}: {e.details()}")
        err = errors.from_rpc_error(e, what)
        if code == grpc.StatusCode.UNAVAILABLE and self._tls:
            err.message += ("\n  over TLS this is also what a refused handshake looks like: "
                            "check ca_cert (the server's CA), and under mutual TLS cert/key")
        return err

    def _pause(self, seconds):
        """Waits `seconds`, or less when the channel is READY again, asking it to connect
        meanwhile: left alone, gRPC retries a lost connection only when its own backoff
        (growing to minutes) expires, long after a restarted server is back (client/python
        README). The CLI resets the backoff; Python's gRPC has no call for that. A channel that
        is READY at once gets the whole pause."""
        start = time.monotonic()
        ready = grpc.channel_ready_future(self._channel)
        try:
            ready.result(timeout=seconds)
        except grpc.FutureTimeoutError:
            return
        finally:
            ready.cancel()
        # Ready at once: the connection was never lost (a draining server answers UNAVAILABLE
        # over it), so wait the whole pause rather than call again at once.
        if time.monotonic() - start < 0.01:
            time.sleep(seconds)

    def _retrying(self, what, fn):
        """Runs fn(); retries it while the server is UNAVAILABLE (restarting), up to
        `reconnect` seconds, but never before the first answer. Raises the typed error."""
        self._ensure_reachable(what)
        until = time.monotonic() + self.reconnect
        wait, said = 0.1, False
        while True:
            try:
                result = fn()
                self._ever_connected = True
                return result
            except grpc.RpcError as e:
                if (e.code() != grpc.StatusCode.UNAVAILABLE or not self._ever_connected
                        or time.monotonic() > until):
                    raise self._error(e, what) from None
                if not said:
                    log.warning("%s: server unavailable (%s); retrying for up to %g s", what,
                                e.details(), self.reconnect)
                    said = True
                self._pause(wait)
                wait = min(wait * 2, 2.0)

    def _unary(self, what, method, request, retry=True, extra_metadata=()):
        def call():
            return method(request, timeout=self.timeout,
                          metadata=self._metadata() + tuple(extra_metadata))

        if retry:
            return self._retrying(what, call)
        self._ensure_reachable(what)
        try:
            return call()
        except grpc.RpcError as e:
            raise self._error(e, what) from None

    # ---- uploads and volumes --------------------------------------------------------------

    def _upload_blob(self, f, attempts=4):
        """Uploads f unless the server holds it, resuming from the server's committed size;
        retries a broken stream (UNAVAILABLE, ABORTED, FAILED_PRECONDITION) `attempts` times.
        Raises grpc.RpcError (the caller types it)."""
        last = None
        for attempt in range(attempts):
            if attempt:
                time.sleep(0.2 * (2 ** attempt))
            try:
                st = self._uploads.GetUploadStatus(
                    uploads_pb2.GetUploadStatusRequest(sha256=f.sha256, size_bytes=f.size),
                    timeout=self.timeout, metadata=self._metadata())
            except grpc.RpcError as e:
                if e.code() == grpc.StatusCode.UNAVAILABLE:
                    last = e
                    continue
                raise
            if st.complete:
                return
            offset = st.committed_size
            changed = []

            def requests(offset=offset, changed=changed):
                with open(f.path, "rb") as fh:
                    fh.seek(offset)
                    pos, first = offset, True
                    while pos < f.size or first:
                        n = min(_CHUNK, f.size - pos)
                        data = fh.read(n)
                        if len(data) != n:
                            changed.append(True)  # ends the stream early: nothing is committed
                            return
                        req = uploads_pb2.UploadRequest(data=data)
                        if first:
                            req.sha256, req.size_bytes, req.write_offset = f.sha256, f.size, pos
                        yield req
                        first, pos = False, pos + n

            try:
                self._uploads.Upload(requests(),
                                     timeout=self.timeout + (f.size - offset) / _MIN_RATE,
                                     metadata=self._metadata())
                if offset:
                    log.info("resumed upload of %s at byte %d of %d", f.name, offset, f.size)
                return
            except grpc.RpcError as e:
                if changed:
                    raise errors.from_status(grpc.StatusCode.DATA_LOSS,
                                             f"{f.path}: changed while uploading",
                                             "upload " + f.path) from None
                if e.code() not in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.ABORTED,
                                    grpc.StatusCode.FAILED_PRECONDITION):
                    raise
                last = e
        raise last

    def _make_volume(self, input_path, series="", request_id=""):
        """Uploads the files of input_path (a file, a header with its data files, or a DICOM
        folder) and creates a volume; returns its decima.v1.Volume."""
        path = os.fspath(input_path)
        files = _inputs.add_header_data_files(_inputs.collect(path))
        if os.path.isdir(path):
            files, dropped = _inputs.keep_dicom_files(files)
            if dropped:
                log.warning("skipping %d file(s) of %s that are not DICOM images: %s%s",
                            len(dropped), path, " ".join(dropped[:5]),
                            " ..." if len(dropped) > 5 else "")
            if not files:
                raise errors.InputError(
                    f"{path}: no DICOM file in the folder (none has the DICM marker); give a "
                    "volume file or a folder of DICOM images")
        _inputs.hash_files(files)
        volume = volumes_pb2.Volume(display_name=os.path.basename(os.path.normpath(path)),
                                    series_instance_uid=series or "")
        manifest = ""
        for f in files:
            self._retrying("upload " + f.path, lambda f=f: self._upload_blob(f))
            volume.files.add(path=f.name, blob="blobs/" + f.sha256)
            manifest += f.name + "\n" + f.sha256 + "\n"
        if request_id:
            # Derived from the job's request id and the files, so a retried submit finds the
            # same volume (the CLI derives it the same way).
            text = request_id + "\n" + (series or "") + "\n" + manifest
            vol_request_id = "vol-" + hashlib.sha256(text.encode()).hexdigest()[:32]
        else:
            vol_request_id = str(uuid.uuid4())
        return self._unary("create volume from " + path, self._volumes.CreateVolume,
                           volumes_pb2.CreateVolumeRequest(volume=volume,
                                                           request_id=vol_request_id))

    # ---- jobs -----------------------------------------------------------------------------

    def _spec(self, spec):
        """A decima.v1.JobSpec from submit()'s keywords; InputError naming a bad one."""
        out = jobs_pb2.JobSpec()
        for key, value in spec.items():
            field = _SPEC_KEYS.get(key)
            if field is None:
                raise errors.InputError(
                    f"submit: unknown job parameter '{key}' (one of "
                    f"{', '.join(sorted(_SPEC_KEYS))}, series, request_id, label_map)")
            if value is None:
                continue
            try:
                if field == "policy":
                    name = value.lower() if isinstance(value, str) else None
                    if name not in _POLICIES:
                        raise ValueError("not one of paper, tetfusion, field")
                    out.policy = _POLICIES[name]
                elif field == "weights":
                    for wname, wvalue in dict(value).items():
                        wfield = _WEIGHTS.get(str(wname).lower())
                        if wfield is None:
                            raise ValueError(f"unknown weight '{wname}' (w_r, w_g, w_s, w_v, "
                                             "w_n)")
                        setattr(out.weights, wfield, float(wvalue))
                elif field == "views":
                    out.views.extend(_views(value))
                elif field == "outputs":
                    out.outputs.extend(_names(value, key))
                elif field == "class_means":
                    out.class_means.extend(float(v) for v in value)
                elif field == "region_names":
                    # Kept as given (the server checks them and names the bad one); as the
                    # CLI, the names set K when regions is not given.
                    if isinstance(value, str):
                        value = value.split(",")
                    out.region_names.extend(str(v) for v in value)
                    if "regions" not in spec:
                        out.regions = len(out.region_names)
                elif field == "min_psnr":
                    # Checked here too so nothing is uploaded for a floor the server refuses.
                    floor = float(value)
                    if not (math.isfinite(floor) and floor > 0):
                        raise ValueError("expected a PSNR floor in dB, finite and > 0")
                    out.min_psnr = floor
                else:
                    setattr(out, field, value)
            except errors.DecimaError:
                raise
            except (TypeError, ValueError) as e:
                raise errors.InputError(f"submit: {key}={value!r}: {e}") from None
        return out

    def submit(self, path_or_folder, *, series=None, label_map=None, request_id=None, **spec):
        """Uploads a volume (a file, a .mhd/.nhdr header with its data, or a DICOM folder)
        and queues a job; returns its Job.

        spec: the job's parameters (decima.v1.JobSpec; unset ones take the server's
        defaults): regions, class_means, region_names (["air", "brain", "bone"] or
        "air,brain,bone": one per region, in label order), target_reduction (or reduction), error_tolerance (or
        tolerance), policy ("field", "paper", "tetfusion"), weights ({"w_r": 10, ...}),
        views (["anterior", "30:20"] or "anterior,lateral"), image_size, transfer_function,
        outputs (["vtu", "labels", ...]), vtu_compression_level (or vtu_level),
        mesh_compression ("zlib" or "lzma": mesh.vtu's compressor), min_psnr (a
        PSNR floor in dB, field policy: as far as possible while the PSNR stays >= it; the
        reduction, if given, is the maximum), stream_slab_voxels (simplify in slabs of this
        many voxel layers, >= 4, for about half the memory; 0 = in memory; unset: the server
        streams only a job that does not fit in memory).
        series: the SeriesInstanceUID to use when a DICOM folder holds several.
        label_map: a label map on the same grid (a file), instead of the segmentation.
        request_id: the AIP-155 idempotency key; a retried submit with it returns the same job.

        The local checks come first (InputError, MissingInputError: nothing is sent). When the
        server refuses the job, the volumes made for it are deleted again (not with a
        request_id: they may belong to the job it made first; nor a volume the server reused,
        which the caller had before).
        """
        job_spec = self._spec(spec)
        _inputs.collect(path_or_folder)  # a missing input fails before any call
        if label_map is not None:
            _inputs.collect(label_map)
        self._ensure_reachable("submit")
        self._check_job_memory(path_or_folder, job_spec)
        volume = self._make_volume(path_or_folder, series or "", request_id or "")
        job_spec.volume = volume.name
        # A reused volume is the caller's from before: never deleted on a refusal.
        made = [volume.name] if not volume.reused else []
        if label_map is not None:
            labels = self._make_volume(
                label_map, "", (request_id + "/label-map") if request_id else "")
            job_spec.label_map = labels.name
            if not labels.reused:
                made.append(labels.name)
        req = jobs_pb2.CreateJobRequest(spec=job_spec, request_id=request_id or str(uuid.uuid4()))
        try:
            job = self._unary("submit", self._jobs.CreateJob, req,
                              extra_metadata=self._create_job_metadata)
        except errors.DecimaError:
            if not request_id:
                for name in made:
                    if name:
                        try:
                            self._volumes.DeleteVolume(
                                volumes_pb2.DeleteVolumeRequest(name=name),
                                timeout=self.timeout, metadata=self._metadata())
                        except grpc.RpcError:
                            pass  # the job's refusal is the error to report
            raise
        return Job(self, job)

    def _check_job_memory(self, path, job_spec):
        """Issue 30: a job that cannot fit the server's memory limit is refused before its
        volume is uploaded (ResourceExhausted with the server's message: size, estimate, limit,
        the flag). Not checked: a DICOM folder (its dims are known only after reading the
        series), a header _header.read_dims cannot parse (the upload goes on and CreateVolume
        names the problem), a server older than the RPC (UNIMPLEMENTED: CreateJob refuses)."""
        dims = _header.read_dims(path)
        if dims is None:
            return
        req = jobs_pb2.CheckJobMemoryRequest(
            spec=job_spec, display_name=os.path.basename(os.fspath(path)), dims=list(dims),
            size_bytes=os.path.getsize(path))
        try:
            self._unary("submit", self._jobs.CheckJobMemory, req)
        except errors.Unimplemented:
            return

    def _resolve(self, job):
        """A job name from a Job, "jobs/{id}", an id, or a unique prefix of one."""
        if isinstance(job, Job):
            return job.name
        arg = str(job)
        if arg.startswith("jobs/"):
            return arg
        if len(arg) >= 16:
            return "jobs/" + arg
        if not arg:
            raise errors.InputError("JOB is empty")
        matches = [j.name for j in self.list() if j.name[len("jobs/"):].startswith(arg)]
        if len(matches) == 1:
            return matches[0]
        if not matches:
            raise errors.NotFound(f"no job id starts with '{arg}' (list() shows the jobs)",
                                  code=grpc.StatusCode.NOT_FOUND)
        shown = " ".join(m[len("jobs/"):] for m in matches[:10])
        raise errors.InputError(f"'{arg}' is ambiguous: {len(matches)} jobs start with it: "
                                f"{shown}{' ...' if len(matches) > 10 else ''}")

    def job(self, job):
        """The Job named by a Job, "jobs/{id}", an id or a unique id prefix (fetched now)."""
        name = self._resolve(job)
        return Job(self, self._unary("status " + name, self._jobs.GetJob,
                                     jobs_pb2.GetJobRequest(name=name)))

    def list(self, states=None):
        """Every job (newest first), or those in `states` ("succeeded", jobs_pb2.FAILED, ...)."""
        req = jobs_pb2.ListJobsRequest(page_size=1000)
        for s in states or ():
            if isinstance(s, str):
                if s.upper() not in ("QUEUED", "RUNNING", "SUCCEEDED", "FAILED", "CANCELLED"):
                    raise errors.InputError(f"state {s}: not one of queued, running, succeeded, "
                                            "failed, cancelled")
                s = jobs_pb2.JobState.Value(s.upper())
            req.states.append(s)
        out = []
        for _ in range(_MAX_PAGES):
            resp = self._unary("list", self._jobs.ListJobs, req)
            out.extend(Job(self, j) for j in resp.jobs)
            if not resp.next_page_token:
                break
            req.page_token = resp.next_page_token
        return out

    def cancel(self, job):
        """Cancels a job and waits (within `timeout`) until it stopped; returns the Job.
        DeadlineExceeded when it is still running after `timeout`."""
        name = self._resolve(job)
        proto = self._unary("cancel " + name, self._jobs.CancelJob,
                            jobs_pb2.CancelJobRequest(name=name), retry=False)
        until = time.monotonic() + self.timeout
        while proto.state not in _FINAL:
            if time.monotonic() > until:
                raise errors.DeadlineExceeded(
                    f"cancel {name}: DEADLINE_EXCEEDED: still {jobs_pb2.JobState.Name(proto.state)}"
                    f" after {self.timeout:g} s", what="cancel " + name,
                    code=grpc.StatusCode.DEADLINE_EXCEEDED)
            time.sleep(0.05)
            proto = self._unary("status " + name, self._jobs.GetJob,
                                jobs_pb2.GetJobRequest(name=name), retry=False)
        return Job(self, proto)

    def delete(self, job, volume=False):
        """Deletes a finished job with its artifacts (FailedPrecondition while it runs: cancel
        it first); volume=True also deletes its input volumes when no other job uses them."""
        name = self._resolve(job)
        proto = self._unary("delete " + name, self._jobs.GetJob, jobs_pb2.GetJobRequest(name=name),
                            retry=False)
        self._unary("delete " + name, self._jobs.DeleteJob, jobs_pb2.DeleteJobRequest(name=name),
                    retry=False)
        if volume:
            candidates = {v for v in (proto.spec.volume, proto.spec.label_map) if v}
            used = set()
            for j in self.list():
                used.update(v for v in (j.proto.spec.volume, j.proto.spec.label_map) if v)
            for v in sorted(candidates - used):
                self._unary("delete " + v, self._volumes.DeleteVolume,
                            volumes_pb2.DeleteVolumeRequest(name=v), retry=False)

    def series(self):
        """The series the server's DICOM receiver got (decima.v1.ReceivedSeries, newest
        arrival first; a submitter sees only the series it owns)."""
        req = volumes_pb2.ListReceivedSeriesRequest(page_size=1000)
        out = []
        for _ in range(_MAX_PAGES):
            resp = self._unary("series", self._volumes.ListReceivedSeries, req)
            out.extend(resp.received_series)
            if not resp.next_page_token:
                break
            req.page_token = resp.next_page_token
        return out


class Job:
    """A job on the server. `proto` is the newest decima.v1.Job this object saw (refresh()
    fetches it again); `name`, `state` ("RUNNING", ...) and `progress` read from it."""

    def __init__(self, client, proto):
        self._client = client
        self.proto = proto

    @property
    def name(self):
        return self.proto.name

    @property
    def state(self):
        return jobs_pb2.JobState.Name(self.proto.state)

    @property
    def progress(self):
        return self.proto.progress

    @property
    def overall(self):
        """Overall progress 0..1 across the stages (1 once SUCCEEDED), as `decima watch`."""
        if self.proto.state == jobs_pb2.SUCCEEDED:
            return 1.0
        return overall_fraction(self.proto.progress, "curve" in self.proto.spec.outputs)

    @property
    def metrics(self):
        """metrics.json of a succeeded job as a dict ({} before)."""
        return json.loads(self.proto.metrics_json) if self.proto.metrics_json else {}

    def __repr__(self):
        return f"<decima_client.Job {self.name} {self.state}>"

    def refresh(self):
        self.proto = self._client._unary("get " + self.name, self._client._jobs.GetJob,
                                         jobs_pb2.GetJobRequest(name=self.name))
        return self

    def watch(self, heartbeats=False):
        """Yields the job's events (decima.v1.JobEvent) until it is final: first a snapshot
        (the job as it is), then every stored and live progress and state change in sequence
        order (heartbeats too with heartbeats=True). Reconnects with the last sequence it saw
        when the server goes away, for up to the client's `reconnect` seconds, so no event is
        missed or repeated. Afterwards `proto` is the final job."""
        c = self._client
        what = "watch " + self.name
        c._ensure_reachable(what)
        last, attempts, wait = 0, 0, 0.1
        give_up = time.monotonic() + c.reconnect
        sent_snapshot = False
        while True:
            got_event = False
            call = c._jobs.WatchJob(jobs_pb2.WatchJobRequest(name=self.name, after_sequence=last),
                                    timeout=c.timeout, metadata=c._metadata())
            try:
                for ev in call:
                    got_event = True
                    c._ever_connected = True
                    if attempts:
                        log.info("%s: reconnected to %s after %d attempt(s)", what, c.address,
                                 attempts)
                        attempts = 0
                    give_up, wait = time.monotonic() + c.reconnect, 0.1
                    kind = ev.WhichOneof("kind")
                    if kind == "snapshot":
                        self.proto = ev.snapshot
                        if not sent_snapshot:
                            sent_snapshot = True
                            yield ev
                        continue
                    if kind == "heartbeat":
                        if heartbeats:
                            yield ev
                        continue
                    last = ev.sequence
                    if kind == "progress":
                        self.proto.progress.CopyFrom(ev.progress)
                    elif kind == "state_change":
                        self.proto.state = ev.state_change.state
                    yield ev
                # The stream ends (OK) after the event that made the job final.
                self.refresh()
                return
            except grpc.RpcError as e:
                code = e.code()
                if code == grpc.StatusCode.DEADLINE_EXCEEDED and got_event:
                    continue  # this stream's deadline: go on from the last sequence
                went_away = code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED)
                if went_away and c._ever_connected and time.monotonic() < give_up:
                    attempts += 1
                    if attempts == 1:  # one line per outage, not per attempt
                        why = ("the server closed the stream" if code == grpc.StatusCode.CANCELLED
                               else e.details())
                        log.warning("%s: server unavailable (%s); reconnecting for up to %g s",
                                    what, why, c.reconnect)
                    c._pause(wait)
                    wait = min(wait * 2, 1.0)
                    continue
                if attempts:
                    log.warning("%s: gave up after %d reconnection attempts", what, attempts)
                if code == grpc.StatusCode.DEADLINE_EXCEEDED and c._ever_connected:
                    raise errors.DeadlineExceeded(
                        f"{what}: DEADLINE_EXCEEDED: no event from the server within "
                        f"{c.timeout:g} s (it sends a heartbeat every few seconds)", what=what,
                        code=code) from None
                raise c._error(e, what) from None
            finally:
                call.cancel()  # also when the caller stops iterating

    def wait(self, timeout=None):
        """Watches the job until it is final and returns self when it SUCCEEDED; raises
        JobFailed or JobCancelled (with the job's error) otherwise, DeadlineExceeded when
        `timeout` seconds pass first (the job goes on on the server)."""
        end = None if timeout is None else time.monotonic() + timeout
        for _ in self.watch(heartbeats=True):
            if end is not None and time.monotonic() > end:
                raise errors.DeadlineExceeded(
                    f"wait {self.name}: DEADLINE_EXCEEDED: not final after {timeout:g} s (the job "
                    "goes on on the server)", what="wait " + self.name,
                    code=grpc.StatusCode.DEADLINE_EXCEEDED)
        return self._check_succeeded()

    def _check_succeeded(self, what=""):
        """Returns self for a SUCCEEDED job; raises JobFailed, JobCancelled or (still running)
        FailedPrecondition worded as the CLI: "jobs/x FAILED: why" after a watch,
        "fetch jobs/x: the job is FAILED: why" for a fetch (`what` "fetch jobs/x")."""
        if self.proto.state == jobs_pb2.SUCCEEDED:
            return self
        msg = self.proto.error.message
        state = self.state + (": " + msg if msg else "")
        text = f"{what}: the job is {state}" if what else f"{self.name} {state}"
        if self.proto.state == jobs_pb2.FAILED:
            raise errors.JobFailed(text, job=self.proto, what=what)
        if self.proto.state == jobs_pb2.CANCELLED:
            raise errors.JobCancelled(text, job=self.proto, what=what)
        raise errors.FailedPrecondition(text, what=what, code=grpc.StatusCode.FAILED_PRECONDITION)

    def cancel(self):
        self.proto = self._client.cancel(self).proto
        return self

    def delete(self, volume=False):
        self._client.delete(self, volume=volume)

    def level(self, reduction, outputs=None, timeout=None):
        """This job's mesh at another reduction, taken from its level record (a job submitted
        with the "levels" output) without simplifying again: the server runs a level job
        (spec.levels_of) on the same volume and segmentation. Waits for it (timeout seconds,
        None = no limit) and returns it. outputs: the kinds it writes ("vtu", "msh", "medit",
        "stl", "glb", "labels", "images", "segmentation", "report"; default ["vtu"]).
        FailedPrecondition when this job kept no record, InvalidArgument (with the recorded
        range) for a reduction past it."""
        c = self._client
        kinds = [o.lower() for o in _names(outputs, "outputs") if o.lower() in _LEVEL_KINDS]
        spec = jobs_pb2.JobSpec(levels_of=self.name, target_reduction=float(reduction),
                                outputs=list(dict.fromkeys(kinds)) or ["vtu"],
                                views=list(self.proto.spec.views),
                                transfer_function=self.proto.spec.transfer_function)
        if self.proto.spec.HasField("image_size"):
            spec.image_size = self.proto.spec.image_size
        req = jobs_pb2.CreateJobRequest(spec=spec, request_id=str(uuid.uuid4()))
        job = Job(c, c._unary(f"fetch {self.name} --reduction", c._jobs.CreateJob, req,
                              extra_metadata=c._create_job_metadata))
        return job.wait(timeout=timeout)

    def fetch(self, out_dir, outputs=None, reduction=None):
        """Downloads the artifacts of a succeeded job into out_dir (created if needed) and
        returns their paths. outputs: file names ("mesh.vtu") or kinds ("vtu", "msh",
        "medit", "levels", "labels", "images", "segmentation", "report", "curve", "metrics"), as
        a list or comma-separated; None for all. Each file goes to NAME.part first (an interrupted
        fetch resumes from its size), is checked against the server's size and sha256, then
        renamed.

        reduction: None for this job's own artifacts; a value takes the mesh at that reduction
        from the job's level record (level(), as `decima fetch JOB --reduction R`) and fetches
        the level job's artifacts, its outputs chosen by the kinds in outputs (default vtu)."""
        if reduction is not None:
            return self.level(reduction, outputs).fetch(out_dir, outputs)
        c = self._client
        only = _names(outputs, "outputs")
        if self.proto.state != jobs_pb2.SUCCEEDED or not self.proto.artifacts:
            self.refresh()
        self._check_succeeded("fetch " + self.name)
        for o in only:
            if not any(_matches(a.file_name, [o]) for a in self.proto.artifacts):
                names = " ".join(a.file_name for a in self.proto.artifacts)
                raise errors.InputError(
                    f"fetch outputs={o}: no such artifact in {self.name}; it has: {names} (or the "
                    "kinds vtu, msh, medit, labels, images, segmentation, report, curve, metrics)")
        out_dir = os.fspath(out_dir)
        paths = []
        for a in self.proto.artifacts:
            if _matches(a.file_name, only):
                paths.append(c._retrying("fetch " + a.name,
                                         lambda a=a: self._download(a, out_dir)))
        metrics = os.path.join(out_dir, "metrics.json")
        if (self.proto.metrics_json and _matches("metrics.json", only)
                and metrics not in paths):
            if not os.path.exists(metrics):
                with open(metrics, "w", encoding="utf-8") as f:
                    f.write(self.proto.metrics_json)
            paths.append(metrics)
        return paths

    def label_map(self, out_dir=None):
        """labels.nii.gz as a numpy array indexed [x, y, z] (needs numpy and python3-vtk9;
        MissingDependencyError without). Fetched into out_dir, or a temporary folder."""
        from . import _arrays

        return _arrays.label_map(self, out_dir)

    def mesh(self, out_dir=None):
        """mesh.vtu as numpy arrays: {"points": (N, 3) mm, "tets": (M, 4) vertex indices,
        "scalar", "label", ... (the file's point and cell arrays)} (needs numpy and
        python3-vtk9; MissingDependencyError without)."""
        from . import _arrays

        return _arrays.mesh(self, out_dir)

    def _download(self, artifact, out_dir):
        """One artifact via FILE.part, resumed from its size, checked, renamed; its path.
        Raises grpc.RpcError for the call, DecimaError for the rest."""
        c = self._client
        what = "fetch " + artifact.name
        try:
            os.makedirs(out_dir, exist_ok=True)
        except OSError as e:
            raise errors.InputError(f"{out_dir}: {e.strerror}") from None
        name = artifact.file_name
        if not name or "/" in name or name.startswith("."):
            raise errors.from_status(grpc.StatusCode.INTERNAL,
                                     f"server sent a bad artifact name '{name}'", what)
        final = os.path.join(out_dir, name)
        part = final + ".part"
        have = os.path.getsize(part) if os.path.exists(part) else 0
        if have > artifact.size_bytes:
            os.remove(part)
            have = 0
        if have < artifact.size_bytes:
            call = c._artifacts.ReadArtifact(
                artifacts_pb2.ReadArtifactRequest(name=artifact.name, read_offset=have),
                timeout=c.timeout + (artifact.size_bytes - have) / _MIN_RATE,
                metadata=c._metadata())
            try:
                with open(part, "ab") as out:
                    for chunk in call:
                        if chunk.offset != have:
                            raise errors.from_status(grpc.StatusCode.DATA_LOSS,
                                                     "artifact chunk out of order", what)
                        out.write(chunk.data)
                        have += len(chunk.data)
            finally:
                call.cancel()
        h = hashlib.sha256()
        size = 0
        with open(part, "rb") as f:
            for block in iter(lambda: f.read(_CHUNK), b""):
                h.update(block)
                size += len(block)
        if size != artifact.size_bytes or (artifact.sha256 and h.hexdigest() != artifact.sha256):
            os.remove(part)
            raise errors.from_status(
                grpc.StatusCode.DATA_LOSS,
                f"{name}: downloaded bytes do not match the server's size/sha256", what)
        os.replace(part, final)
        return final
