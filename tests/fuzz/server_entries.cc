// Fuzz entries of the server's request handling: Upload + GetUploadStatus, and CreateVolume
// (manifest -> VolumeCatalog -> header probe) + GetVolume + DeleteVolume, through the real
// services over gRPC on a loopback TCP port, with a real SQLite job store and a LocalBlobStore in
// a temporary data dir of this process. The stores are emptied after every input so the state
// stays small whatever the campaign's length.
#include <unistd.h>

#include <grpcpp/grpcpp.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "server/api/service.h"
#include "server/files/blob_store.h"
#include "server/files/data_dir.h"
#include "server/jobs/worker_pool.h"
#include "server/store/event_bus.h"
#include "server/store/job_store.h"
#include "server/util/sha256.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

// LeakSanitizer (libFuzzer checks after inputs): gRPC's synchronous server keeps the objects of
// the polling threads it starts and retires (the thread itself, its list entry once completed,
// the call allocation of a registered method it was waiting in) until the server shuts down,
// which this harness never does (one server for the life of the process). Found by
// create_volume_fuzz; only those gRPC allocations are exempt, any leak of our code is still
// reported.
extern "C" const char* __lsan_default_suppressions() {
  return "leak:grpc::ThreadManager::MainWorkLoop\n"
         "leak:grpc::ThreadManager::MarkAsCompleted\n"
         "leak:grpc::Server::SyncRequestThreadManager::AddSyncMethod\n"
         "leak:grpc_core::Thread::Thread\n";
}

namespace decima::fuzz {
namespace {

namespace fs = std::filesystem;
using server::LocalBlobStore;

// The services over real stores in <tmp>/decima-server-fuzz-<pid>; built on first use and kept
// for the life of the process (libFuzzer calls the entry millions of times).
struct Harness {
  fs::path dir;
  server::EventBus bus;
  std::unique_ptr<server::JobStore> store;
  std::unique_ptr<LocalBlobStore> blobs;
  std::unique_ptr<server::WorkerPool> pool;  // never started: no job runs
  std::unique_ptr<server::Services> services;
  std::unique_ptr<grpc::Server> server;
  std::unique_ptr<v1::Uploads::Stub> uploads;
  std::unique_ptr<v1::Volumes::Stub> volumes;

  Harness() {
    dir = fs::temp_directory_path() / ("decima-server-fuzz-" + std::to_string(::getpid()));
    std::error_code ec;
    fs::remove_all(dir, ec);
    fs::create_directories(dir);
    auto s = server::OpenSqliteJobStore((dir / "jobs.sqlite").string());
    Require(s.ok(), "the job store opens");
    store = std::move(*s);
    auto b = LocalBlobStore::Open(dir / "blobs", /*fsync=*/false);
    Require(b.ok(), "the blob store opens");
    blobs = std::move(*b);
    server::WorkerPoolOptions wo;
    wo.owner = "fuzz";
    pool = std::make_unique<server::WorkerPool>(store.get(), wo);
    server::ServiceOptions so;
    so.data_dir = server::DataDir(dir);
    so.max_upload_bytes = 1 << 20;  // small, so the limit is reachable by fuzzed sizes
    services = std::make_unique<server::Services>(so, store.get(), blobs.get(), &bus, pool.get());
    // Loopback TCP, the transport clients use. The in-process transport was tried first: there
    // a client's Write blocks for ever once the server has answered without reading the rest of
    // the stream (a deduplicated upload followed by a large chunk), which TCP does not do
    // (HardeningE2E.AnUploadOfABlobTheServerHolds...): the fuzzer was timing gRPC's inproc
    // transport, not the server.
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(services->uploads());
    builder.RegisterService(services->volumes());
    server = builder.BuildAndStart();
    Require(server != nullptr && port > 0, "the loopback server starts");
    auto channel = grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                       grpc::InsecureChannelCredentials());
    uploads = v1::Uploads::NewStub(channel);
    volumes = v1::Volumes::NewStub(channel);
  }

  // Every blob and partial upload and every volume folder gone (the store rows of volumes are
  // removed by DeleteVolume in the entry); the folders are made again by Open.
  void Reset() {
    std::error_code ec;
    fs::remove_all(dir / "blobs", ec);
    fs::remove_all(dir / "volumes", ec);
    Require(LocalBlobStore::Open(dir / "blobs", false).ok(), "the blob store reopens");
  }
};

Harness& TheHarness() {
  static Harness* h = new Harness();  // never destroyed: the gRPC server outlives every input
  return *h;
}

// Consumes the fuzz input front to back; past the end it yields zeros and empty strings.
class Input {
 public:
  Input(const uint8_t* data, size_t size) : p_(data), n_(size) {}
  uint8_t Byte() {
    if (n_ == 0) return 0;
    --n_;
    return *p_++;
  }
  uint64_t Varint() {
    uint64_t v = 0;
    for (int shift = 0; shift < 64; shift += 7) {
      const uint8_t b = Byte();
      v |= uint64_t(b & 0x7f) << shift;
      if (!(b & 0x80)) break;
    }
    return v;
  }
  int64_t SignedVarint() {  // zigzag, so small negative values are short
    const uint64_t v = Varint();
    return static_cast<int64_t>(v >> 1) ^ -static_cast<int64_t>(v & 1);
  }
  std::string Take(size_t k) {
    k = std::min(k, n_);
    std::string s(reinterpret_cast<const char*>(p_), k);
    p_ += k;
    n_ -= k;
    return s;
  }
  std::string Rest() { return Take(n_); }
  size_t left() const { return n_; }

 private:
  const uint8_t* p_;
  size_t n_;
};

// proto3 string fields must be UTF-8: gRPC refuses anything else (INTERNAL, "failed to parse")
// before a handler sees it, so fuzzed strings are kept to ASCII to reach the handlers.
std::string Ascii(std::string s) {
  for (char& c : s) c &= 0x7f;
  return s;
}

std::string Digest(std::string_view bytes) {
  server::Sha256 h;
  h.Update(bytes.data(), bytes.size());
  return h.HexDigest();
}

std::string FileBytes(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Codes a handler may answer with for bad input; anything else (UNKNOWN, INTERNAL, ...) means
// an exception, an unexpected store failure or an unhandled case.
bool ExpectedCode(grpc::StatusCode c) {
  switch (c) {
    case grpc::StatusCode::OK:
    case grpc::StatusCode::INVALID_ARGUMENT:
    case grpc::StatusCode::NOT_FOUND:
    case grpc::StatusCode::FAILED_PRECONDITION:
    case grpc::StatusCode::ABORTED:
    case grpc::StatusCode::ALREADY_EXISTS:
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
    case grpc::StatusCode::OUT_OF_RANGE:
    case grpc::StatusCode::UNIMPLEMENTED:  // core/io: a valid file with an unsupported feature
      return true;
    default:
      return false;
  }
}

void RequireExpected(const grpc::Status& s, const char* what) {
  if (ExpectedCode(s.error_code())) return;
  std::fprintf(stderr, "%s answered code %d: %s\n", what, int(s.error_code()),
               s.error_message().c_str());
  Require(false, "a handler answered with an unexpected status code");
}

// One Upload stream: the first message declares (sha, size, offset); `data` goes out in chunks
// of `chunk` bytes (the first with the declaration when `data_in_first`).
grpc::Status Upload(Harness& h, const std::string& sha, int64_t size, int64_t offset,
                    std::string_view data, size_t chunk, bool data_in_first, v1::Blob* blob) {
  grpc::ClientContext ctx;
  auto writer = h.uploads->Upload(&ctx, blob);
  v1::UploadRequest req;
  req.set_sha256(sha);
  req.set_size_bytes(size);
  req.set_write_offset(offset);
  size_t at = 0;
  if (data_in_first && !data.empty()) {
    const size_t k = std::min(chunk, data.size());
    req.set_data(std::string(data.substr(0, k)));
    at = k;
  }
  bool open = writer->Write(req);
  while (open && at < data.size()) {
    const size_t k = std::min(chunk, data.size() - at);
    v1::UploadRequest next;
    next.set_data(std::string(data.substr(at, k)));
    at += k;
    open = writer->Write(next);
  }
  writer->WritesDone();
  return writer->Finish();
}

// A blob the server says it holds completely must be exactly the bytes of its digest and size.
void CheckHeld(Harness& h, const std::string& sha, int64_t size) {
  grpc::ClientContext ctx;
  v1::GetUploadStatusRequest q;
  q.set_sha256(sha);
  q.set_size_bytes(size);
  v1::UploadStatus st;
  const grpc::Status s = h.uploads->GetUploadStatus(&ctx, q, &st);
  Require(s.ok(), "GetUploadStatus of an uploaded blob answers");
  Require(st.complete() && st.committed_size() == size, "an uploaded blob is complete");
  auto path = h.blobs->LocalPath(sha);
  Require(path.ok(), "an uploaded blob has a path");
  const std::string bytes = FileBytes(*path);
  Require(int64_t(bytes.size()) == size && Digest(bytes) == sha,
          "the stored bytes are the declared size and digest");
}

}  // namespace

int UploadEntry(const uint8_t* data, size_t size) {
  Harness& h = TheHarness();
  Input in(data, size);
  const uint8_t flags = in.Byte();
  const bool fuzzed_sha = flags & 1, fuzzed_size = flags & 2, interrupted = flags & 4,
             fuzzed_offset = flags & 8, data_in_first = flags & 16, oversized_chunk = flags & 32;
  size_t chunk = 1 + in.Byte() * 7u;
  const std::string sha_bytes = fuzzed_sha ? Ascii(in.Take(64)) : "";
  const int64_t declared_size = fuzzed_size ? in.SignedVarint() : 0;
  const int64_t offset = fuzzed_offset ? in.SignedVarint() : 0;
  const size_t cut = interrupted ? in.Varint() : 0;
  std::string payload = in.Rest();
  // The over-long chunk goes out as one message (1 MiB in 1-byte messages would only time the
  // harness).
  if (oversized_chunk) {
    payload.resize(payload.size() + server::kMaxChunkBytes + 1, 'z');
    chunk = server::kMaxChunkBytes + 1;
  }
  const std::string sha = fuzzed_sha ? sha_bytes : Digest(payload);
  const int64_t sz = fuzzed_size ? declared_size : int64_t(payload.size());
  const bool honest = !fuzzed_sha && !fuzzed_size && !fuzzed_offset && !oversized_chunk &&
                      (!interrupted || cut < payload.size());

  v1::Blob blob;
  grpc::Status s;
  if (interrupted && cut < payload.size()) {
    // The stream ends early: the prefix is kept and the resume continues from it.
    s = Upload(h, sha, sz, offset, std::string_view(payload).substr(0, cut), chunk, data_in_first,
               &blob);
    RequireExpected(s, "Upload (interrupted)");
    if (honest) Require(s.error_code() == grpc::StatusCode::ABORTED, "a short stream is ABORTED");
    grpc::ClientContext ctx;
    v1::GetUploadStatusRequest q;
    q.set_sha256(sha);
    q.set_size_bytes(sz);
    v1::UploadStatus st;
    const grpc::Status gs = h.uploads->GetUploadStatus(&ctx, q, &st);
    RequireExpected(gs, "GetUploadStatus");
    if (honest) {
      Require(gs.ok() && !st.complete() && st.committed_size() == int64_t(cut),
              "the prefix of a short stream is held");
    }
    const int64_t resume = gs.ok() ? st.committed_size() : 0;
    blob.Clear();
    s = Upload(h, sha, sz, fuzzed_offset ? offset : resume,
               std::string_view(payload).substr(std::min<size_t>(resume, payload.size())), chunk,
               data_in_first, &blob);
    RequireExpected(s, "Upload (resumed)");
  } else {
    s = Upload(h, sha, sz, offset, payload, chunk, data_in_first, &blob);
    RequireExpected(s, "Upload");
  }
  SetLastInputAccepted(s.ok());
  if (honest) Require(s.ok(), "an honest upload succeeds");
  if (s.ok()) {
    Require(blob.sha256() == sha && blob.size_bytes() == sz && blob.name() == "blobs/" + sha,
            "the Blob answered names what was uploaded");
    CheckHeld(h, sha, sz);
  }
  h.Reset();
  return 0;
}

int CreateVolumeEntry(const uint8_t* data, size_t size) {
  static const char* kNames[] = {"v.nii", "v.nii.gz", "v.hdr",  "v.img",   "v.mha", "v.mhd",
                                 "a.raw", "a.zraw",   "v.nrrd", "v.nhdr",  "IM0",   "IM1",
                                 "s/IM2", "s",        "x.txt",  "a.raw.gz"};
  Harness& h = TheHarness();
  Input in(data, size);
  const uint8_t head = in.Byte();
  const int nfiles = 1 + head % 4;
  v1::CreateVolumeRequest req;
  v1::Volume* vol = req.mutable_volume();
  vol->set_format(static_cast<v1::VolumeFormat>(((head >> 2) & 7) % 6));  // 5: not a known value
  static int64_t request_count = 0;  // ids unique per input: a deleted volume keeps its id
  if (head & 0x80) req.set_request_id("fuzz-" + std::to_string(++request_count));
  for (int i = 0; i < nfiles && (i == 0 || in.left() > 0); ++i) {
    const uint8_t mode = in.Byte();
    v1::VolumeFile* f = vol->add_files();
    f->set_path((mode & 1) ? Ascii(in.Take(in.Byte())) : kNames[in.Byte() % 16]);
    // File contents are length-prefixed, except the last file's, which is the rest of the input.
    const std::string content = (i + 1 < nfiles) ? in.Take(in.Varint()) : in.Rest();
    const std::string sha = Digest(content);
    switch ((mode >> 1) & 3) {
      case 0:
      case 1: {  // uploaded
        v1::Blob blob;
        const grpc::Status s = Upload(h, sha, content.size(), 0, content, 1 << 16, true, &blob);
        RequireExpected(s, "Upload");
        f->set_blob("blobs/" + sha);
        break;
      }
      case 2:  // named but never uploaded
        f->set_blob("blobs/" + sha);
        break;
      default:  // a malformed blob name
        f->set_blob(Ascii(content.substr(0, 80)));
    }
  }
  v1::Volume created;
  grpc::Status s;
  {
    grpc::ClientContext ctx;
    s = h.volumes->CreateVolume(&ctx, req, &created);
  }
  RequireExpected(s, "CreateVolume");
  SetLastInputAccepted(s.ok());
  const fs::path volumes_dir = h.dir / "volumes";
  if (!s.ok()) {
    std::error_code ec;
    Require(!fs::exists(volumes_dir, ec) || fs::is_empty(volumes_dir, ec),
            "a refused CreateVolume leaves no volume folder");
  } else {
    Require(created.name().rfind("volumes/", 0) == 0, "a created volume has a name");
    const fs::path files = volumes_dir / created.name().substr(8) / "files";
    for (const auto& f : req.volume().files()) {
      Require(fs::is_regular_file(files / f.path()), "every manifest file is materialized");
    }
    for (int64_t d : created.dims()) Require(d >= 1, "parsed dims are positive");
    if (!req.request_id().empty()) {  // a retry answers the same volume
      grpc::ClientContext ctx;
      v1::Volume again;
      Require(h.volumes->CreateVolume(&ctx, req, &again).ok() && again.name() == created.name(),
              "a retried CreateVolume answers the same volume");
    }
    {
      grpc::ClientContext ctx;
      v1::GetVolumeRequest g;
      g.set_name(created.name());
      v1::Volume got;
      Require(h.volumes->GetVolume(&ctx, g, &got).ok() && got.dims_size() == created.dims_size(),
              "GetVolume answers the created volume");
    }
    grpc::ClientContext ctx;
    v1::DeleteVolumeRequest d;
    d.set_name(created.name());
    v1::DeleteVolumeResponse r;
    Require(h.volumes->DeleteVolume(&ctx, d, &r).ok(), "an unused volume can be deleted");
    std::error_code ec;
    Require(!fs::exists(files, ec), "DeleteVolume removes the files");
  }
  h.Reset();
  return 0;
}

}  // namespace decima::fuzz
