#include "client/client_lib.h"

#include <string_view>

#include <fcntl.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>
#include <thread>

#include "client/text.h"
#include "core/common/sha256.h"

namespace decima::client {
namespace fs = std::filesystem;

int ExitCodeFor(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return kOk;
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return kTimeout;
    case grpc::StatusCode::NOT_FOUND:
      return kNotFound;
    case grpc::StatusCode::UNAUTHENTICATED:
      return kUnauthenticated;
    case grpc::StatusCode::PERMISSION_DENIED:
      return kPermissionDenied;
    case grpc::StatusCode::UNAVAILABLE:
      return kUnavailable;
    default:
      return kError;
  }
}

int ExitCodeFor(v1::JobState state) {
  switch (state) {
    case v1::SUCCEEDED:
      return kOk;
    case v1::FAILED:
      return kJobFailed;
    case v1::CANCELLED:
      return kJobCancelled;
    default:
      return kError;
  }
}

std::string StatusCodeName(grpc::StatusCode code) {
  static const char* kNames[] = {"OK",
                                 "CANCELLED",
                                 "UNKNOWN",
                                 "INVALID_ARGUMENT",
                                 "DEADLINE_EXCEEDED",
                                 "NOT_FOUND",
                                 "ALREADY_EXISTS",
                                 "PERMISSION_DENIED",
                                 "RESOURCE_EXHAUSTED",
                                 "FAILED_PRECONDITION",
                                 "ABORTED",
                                 "OUT_OF_RANGE",
                                 "UNIMPLEMENTED",
                                 "INTERNAL",
                                 "UNAVAILABLE",
                                 "DATA_LOSS",
                                 "UNAUTHENTICATED"};
  int c = static_cast<int>(code);
  return c >= 0 && c <= 16 ? kNames[c] : "CODE_" + std::to_string(c);
}

bool CollectInputs(const fs::path& input, std::vector<InputFile>* out, std::string* error) {
  std::error_code ec;
  out->clear();
  if (fs::is_regular_file(input, ec)) {
    InputFile f;
    f.name = input.filename().string();
    f.path = input;
    f.size = static_cast<int64_t>(fs::file_size(input, ec));
    out->push_back(std::move(f));
    return true;
  }
  if (!fs::is_directory(input, ec)) {
    *error = input.string() + ": no such file or folder";
    return false;
  }
  for (auto it = fs::recursive_directory_iterator(input, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    const fs::path& p = it->path();
    if (p.filename().string().rfind('.', 0) == 0) {
      if (it->is_directory(ec)) it.disable_recursion_pending();
      continue;
    }
    // Only the folder's own regular files go up: a symbolic link may point anywhere on this
    // machine (x.zraw -> /etc/passwd), so it is refused by name rather than followed or
    // silently skipped (the user can copy the file in if it belongs to the scan).
    const fs::file_status link_status = it->symlink_status(ec);
    if (ec) break;
    if (fs::is_symlink(link_status)) {
      *error = p.string() + ": is a symbolic link; only regular files inside " + input.string() +
               " are uploaded (copy the file into the folder instead)";
      return false;
    }
    if (!fs::is_regular_file(link_status)) continue;
    InputFile f;
    f.name = fs::relative(p, input, ec).generic_string();
    f.path = p;
    f.size = static_cast<int64_t>(fs::file_size(p, ec));
    out->push_back(std::move(f));
  }
  if (ec) {
    *error = input.string() + ": " + ec.message();
    return false;
  }
  if (out->empty()) {
    *error = input.string() + ": the folder holds no files";
    return false;
  }
  std::sort(out->begin(), out->end(),
            [](const InputFile& a, const InputFile& b) { return a.name < b.name; });
  return true;
}

bool HashInputs(std::vector<InputFile>* files, std::string* error) {
  for (auto& f : *files) {
    Sha256 sha;
    int64_t total = 0;
    if (absl::Status st = HashFilePrefix(f.path, -1, sha, &total); !st.ok()) {
      *error = std::string(st.message());
      return false;
    }
    f.sha256 = sha.HexDigest();
    f.size = total;
  }
  return true;
}

std::unique_ptr<grpc::ClientContext> Connection::Context(bool deadline) const {
  auto ctx = std::make_unique<grpc::ClientContext>();
  if (!token.empty()) ctx->AddMetadata("authorization", "Bearer " + token);
  if (deadline) ctx->set_deadline(std::chrono::system_clock::now() + timeout);
  return ctx;
}

Connection Connect(const std::string& address, const std::string& token, const TlsFiles& tls,
                   std::chrono::milliseconds timeout, std::string* error) {
  std::shared_ptr<grpc::ChannelCredentials> creds = grpc::InsecureChannelCredentials();
  if (tls.any()) {
    grpc::SslCredentialsOptions o;
    auto read = [error](const std::string& flag, const std::string& file, std::string* text) {
      std::ifstream in(file, std::ios::binary);
      std::stringstream ss;
      if (!in || !(ss << in.rdbuf())) {
        *error = flag + " " + file + ": cannot read";
        return false;
      }
      *text = ss.str();
      return true;
    };
    if (tls.cert_file.empty() != tls.key_file.empty()) {
      *error = "--tls-cert and --tls-key go together (a client certificate and its key)";
      return Connection{};
    }
    if (!tls.ca_file.empty() && !read("--ca-cert", tls.ca_file, &o.pem_root_certs)) {
      return Connection{};
    }
    if (!tls.cert_file.empty() && (!read("--tls-cert", tls.cert_file, &o.pem_cert_chain) ||
                                   !read("--tls-key", tls.key_file, &o.pem_private_key))) {
      return Connection{};
    }
    creds = grpc::SslCredentials(o);
  }
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(8 << 20);
  Connection c;
  c.channel = grpc::CreateCustomChannel(address, creds, args);
  c.token = token;
  c.timeout = timeout;
  return c;
}

grpc::Status UploadBlob(const Connection& c, const InputFile& file, const ByteProgress& progress,
                        int attempts, int64_t* resumed_at) {
  auto stub = v1::Uploads::NewStub(c.channel);
  grpc::Status last;
  for (int attempt = 0; attempt < std::max(1, attempts); ++attempt) {
    if (attempt > 0) std::this_thread::sleep_for(std::chrono::milliseconds(200 << attempt));
    v1::GetUploadStatusRequest sreq;
    sreq.set_sha256(file.sha256);
    sreq.set_size_bytes(file.size);
    v1::UploadStatus st;
    last = stub->GetUploadStatus(c.Context().get(), sreq, &st);
    if (!last.ok()) {
      if (last.error_code() == grpc::StatusCode::UNAVAILABLE) continue;
      return last;
    }
    int64_t offset = st.complete() ? file.size : st.committed_size();
    if (attempt == 0 && resumed_at != nullptr) *resumed_at = offset;
    if (st.complete()) {
      if (progress) progress(file.size, file.size);
      return grpc::Status::OK;
    }
    std::ifstream in(file.path, std::ios::binary);
    if (!in)
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, file.path.string() + ": cannot open");
    in.seekg(offset);
    auto ctx = c.Context(/*deadline=*/false);
    v1::Blob blob;
    auto writer = stub->Upload(ctx.get(), &blob);
    v1::UploadRequest req;
    req.set_sha256(file.sha256);
    req.set_size_bytes(file.size);
    req.set_write_offset(offset);
    std::string buf(1 << 20, '\0');
    int64_t pos = offset;
    bool first = true;
    while (pos < file.size || first) {
      size_t n = static_cast<size_t>(std::min<int64_t>(buf.size(), file.size - pos));
      if (n > 0 && !in.read(buf.data(), static_cast<std::streamsize>(n))) {
        ctx->TryCancel();
        return grpc::Status(grpc::StatusCode::DATA_LOSS,
                            file.path.string() + ": changed while uploading");
      }
      req.set_data(buf.data(), n);
      if (!writer->Write(req)) break;  // the server answered early (dedup) or failed
      req.clear_sha256();
      req.clear_size_bytes();
      req.clear_write_offset();
      first = false;
      pos += static_cast<int64_t>(n);
      if (progress) progress(pos, file.size);
    }
    writer->WritesDone();
    last = writer->Finish();
    if (last.ok()) return last;
    auto code = last.error_code();
    if (code != grpc::StatusCode::UNAVAILABLE && code != grpc::StatusCode::ABORTED &&
        code != grpc::StatusCode::FAILED_PRECONDITION) {
      return last;
    }
  }
  return last;
}

grpc::Status DownloadArtifact(const Connection& c, const v1::Artifact& artifact,
                              const fs::path& dir, const ByteProgress& progress, fs::path* path) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec)
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, dir.string() + ": " + ec.message());
  const std::string file = artifact.file_name();
  if (file.empty() || file.find('/') != std::string::npos || file[0] == '.') {
    return grpc::Status(grpc::StatusCode::INTERNAL,
                        "server sent a bad artifact name '" + file + "'");
  }
  fs::path final_path = dir / file;
  fs::path part = dir / (file + ".part");
  int64_t have = fs::exists(part, ec) ? static_cast<int64_t>(fs::file_size(part, ec)) : 0;
  if (have > artifact.size_bytes()) {
    fs::remove(part, ec);
    have = 0;
  }
  auto stub = v1::Artifacts::NewStub(c.channel);
  if (have < artifact.size_bytes()) {
    std::ofstream out(part, std::ios::binary | std::ios::app);
    if (!out)
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, part.string() + ": cannot write");
    v1::ReadArtifactRequest req;
    req.set_name(artifact.name());
    req.set_read_offset(have);
    auto ctx = c.Context(false);
    auto reader = stub->ReadArtifact(ctx.get(), req);
    v1::ReadArtifactResponse chunk;
    while (reader->Read(&chunk)) {
      if (chunk.offset() != have) {
        ctx->TryCancel();
        reader->Finish();
        return grpc::Status(grpc::StatusCode::DATA_LOSS, "artifact chunk out of order");
      }
      out.write(chunk.data().data(), static_cast<std::streamsize>(chunk.data().size()));
      have += static_cast<int64_t>(chunk.data().size());
      if (progress) progress(have, artifact.size_bytes());
    }
    grpc::Status s = reader->Finish();
    out.close();
    if (!s.ok()) return s;
  }
  InputFile check{file, part, 0, ""};
  std::vector<InputFile> one{check};
  std::string err;
  if (!HashInputs(&one, &err)) return grpc::Status(grpc::StatusCode::INTERNAL, err);
  if (one[0].size != artifact.size_bytes() ||
      (!artifact.sha256().empty() && one[0].sha256 != artifact.sha256())) {
    fs::remove(part, ec);
    return grpc::Status(grpc::StatusCode::DATA_LOSS,
                        file + ": downloaded bytes do not match the server's size/sha256");
  }
  fs::rename(part, final_path, ec);
  if (ec)
    return grpc::Status(grpc::StatusCode::INTERNAL, final_path.string() + ": " + ec.message());
  if (path) *path = final_path;
  return grpc::Status::OK;
}

std::string DescribeEvent(const std::string& job, const v1::JobEvent& ev) {
  std::ostringstream s;
  s << job << " #" << ev.sequence() << " ";
  if (ev.has_snapshot()) {
    const auto& j = ev.snapshot();
    s << "snapshot " << v1::JobState_Name(j.state());
    if (!j.progress().stage().empty()) {
      s << " " << j.progress().stage() << " " << static_cast<int>(j.progress().fraction() * 100)
        << "%";
    }
  } else if (ev.has_progress()) {
    const auto& p = ev.progress();
    s << p.stage() << " " << static_cast<int>(p.fraction() * 100) << "%";
    if (!p.message().empty()) s << " " << p.message();
  } else if (ev.has_state_change()) {
    s << v1::JobState_Name(ev.state_change().state());
    if (!ev.state_change().error().message().empty()) {
      s << ": " << ev.state_change().error().message();
    }
  } else if (ev.has_heartbeat()) {
    s << "heartbeat";
  }
  return s.str();
}

std::string ProgressBar(const v1::Progress& p, int width) {
  double f = std::clamp(p.fraction(), 0.0, 1.0);
  int filled = static_cast<int>(f * width + 0.5);
  std::string bar(static_cast<size_t>(filled), '#');
  bar.append(static_cast<size_t>(width - filled), '.');
  char pct[8];
  std::snprintf(pct, sizeof pct, "%3d%%", static_cast<int>(f * 100));
  std::string stage = p.stage();
  stage.resize(std::max<size_t>(stage.size(), 9), ' ');
  std::string msg = p.message().substr(0, 40);
  return stage + " [" + bar + "] " + pct + " " + msg;
}

}  // namespace decima::client

namespace decima::client {
namespace {

std::string Trim(const std::string& s) {
  size_t a = s.find_first_not_of(" \t\r\n"), b = s.find_last_not_of(" \t\r\n");
  return a == std::string::npos ? "" : s.substr(a, b - a + 1);
}

}  // namespace

bool TcpPortAnswers(const std::string& address, std::chrono::milliseconds timeout) {
  std::string a = address;
  for (const char* prefix : {"dns:///", "ipv4:", "ipv6:"}) {
    if (a.rfind(prefix, 0) == 0) a = a.substr(std::strlen(prefix));
  }
  const size_t colon = a.rfind(':');
  if (colon == std::string::npos || a.rfind("unix:", 0) == 0) return false;
  std::string host = a.substr(0, colon), port = a.substr(colon + 1);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  addrinfo hints{};
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* res = nullptr;
  if (getaddrinfo(host.c_str(), port.c_str(), &hints, &res) != 0) return false;
  bool answered = false;
  for (addrinfo* ai = res; ai != nullptr && !answered; ai = ai->ai_next) {
    const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) continue;
    if (::connect(fd, ai->ai_addr, ai->ai_addrlen) == 0) {
      answered = true;
    } else if (errno == EINPROGRESS) {
      pollfd p{fd, POLLOUT, 0};
      int err = 0;
      socklen_t len = sizeof err;
      answered = ::poll(&p, 1, static_cast<int>(timeout.count())) == 1 &&
                 ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &len) == 0 && err == 0;
    }
    ::close(fd);
  }
  freeaddrinfo(res);
  return answered;
}

std::string TerminalSafe(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  auto escape = [&out](const char* fmt, unsigned v) {
    char buf[8];
    std::snprintf(buf, sizeof buf, fmt, v);
    out += buf;
  };
  for (size_t i = 0; i < text.size();) {
    const unsigned char c = static_cast<unsigned char>(text[i]);
    if (c < 0x20 || c == 0x7f) {
      escape("\\x%02x", c);
      ++i;
      continue;
    }
    if (c < 0x80) {
      out += static_cast<char>(c);
      ++i;
      continue;
    }
    // A UTF-8 sequence: its length from the lead byte, then continuation bytes, shortest form.
    const size_t n = c >= 0xc2 && c <= 0xdf   ? 2
                     : c >= 0xe0 && c <= 0xef ? 3
                     : c >= 0xf0 && c <= 0xf4 ? 4
                                              : 0;
    unsigned cp = n == 2 ? c & 0x1f : n == 3 ? c & 0x0f : c & 0x07;
    bool valid = n > 0 && i + n <= text.size();
    for (size_t k = 1; valid && k < n; ++k) {
      const unsigned char cc = static_cast<unsigned char>(text[i + k]);
      valid = (cc & 0xc0) == 0x80;
      cp = (cp << 6) | (cc & 0x3f);
    }
    if (valid && ((n == 3 && cp < 0x800) || (n == 4 && (cp < 0x10000 || cp > 0x10ffff)) ||
                  (cp >= 0xd800 && cp <= 0xdfff))) {
      valid = false;
    }
    if (!valid) {
      escape("\\x%02x", c);
      ++i;
    } else if (cp >= 0x80 && cp <= 0x9f) {
      escape("\\u%04x", cp);
      i += n;
    } else {
      out.append(text.substr(i, n));
      i += n;
    }
  }
  return out;
}

std::string Sha256HexOf(std::string_view bytes) {
  Sha256 sha;
  sha.Update(bytes.data(), bytes.size());
  return sha.HexDigest();
}

bool AddHeaderDataFiles(std::vector<InputFile>* files, std::string* error) {
  if (files->size() != 1) return true;
  const InputFile header = (*files)[0];
  const std::string lname = AsciiLower(header.name);
  const bool mhd = EndsWith(lname, ".mhd"), nhdr = EndsWith(lname, ".nhdr");
  if (!mhd && !nhdr) return true;
  std::ifstream in(header.path);
  if (!in) {
    *error = header.path.string() + ": cannot open";
    return false;
  }
  std::vector<std::string> names;
  std::string line;
  int lineno = 0;
  bool list = false;
  while (std::getline(in, line) && lineno < 10000) {
    ++lineno;
    if (list) {
      if (!Trim(line).empty()) names.push_back(Trim(line));
      continue;
    }
    std::string key, value;
    if (mhd) {
      auto eq = line.find('=');
      if (eq == std::string::npos) continue;
      key = AsciiLower(Trim(line.substr(0, eq)));
      value = Trim(line.substr(eq + 1));
      if (key != "elementdatafile") continue;
    } else {
      if (Trim(line).empty()) break;  // the blank line ends an NRRD header
      auto colon = line.find(':');
      if (colon == std::string::npos) continue;
      key = AsciiLower(Trim(line.substr(0, colon)));
      value = Trim(line.substr(colon + 1));
      if (!value.empty() && value[0] == '=') continue;  // key:=value pairs
      if (key != "data file" && key != "datafile") continue;
    }
    const std::string lv = AsciiLower(value);
    if (lv == "local") return true;
    if (lv.rfind("list", 0) == 0) {
      list = true;
      continue;
    }
    if (value.find('%') != std::string::npos || value.find(' ') != std::string::npos) {
      *error = header.path.string() + ":" + std::to_string(lineno) + ": data file '" + value +
               "' is a pattern; copy the slices and a LIST header into one folder";
      return false;
    }
    names.push_back(value);
    if (mhd) break;
  }
  if (names.empty()) {
    if (mhd) {
      *error = header.path.string() +
               ": no ElementDataFile line (a MetaImage header names its "
               "data file)";
      return false;
    }
    return true;  // an NRRD with attached data
  }
  const fs::path dir = header.path.parent_path();
  for (const auto& n : names) {
    const fs::path rel = fs::path(n).lexically_normal();
    if (rel.is_absolute() || rel.empty() || *rel.begin() == "..") {
      *error = header.path.string() + ": data file '" + n +
               "' is outside the header's folder; copy it beside the header";
      return false;
    }
    InputFile f;
    f.name = rel.generic_string();
    f.path = dir / rel;
    std::error_code ec;
    // Every component below the header's folder, not only the last: a linked folder leads
    // anywhere (issue 35 part 5).
    fs::path prefix = dir;
    for (const auto& part : rel.parent_path()) {
      prefix /= part;
      if (fs::is_symlink(fs::symlink_status(prefix, ec))) {
        *error = header.path.string() + ": the path of its data file " + f.path.string() +
                 " goes through the symbolic link " + prefix.string() +
                 " (copy the data beside the header instead)";
        return false;
      }
    }
    const fs::file_status st = fs::symlink_status(f.path, ec);
    if (ec || !fs::is_regular_file(st)) {
      *error = header.path.string() + ": its data file " + f.path.string() +
               (fs::is_symlink(st) ? " is a symbolic link (copy the file instead)"
                                   : " does not exist or is not a regular file");
      return false;
    }
    f.size = static_cast<int64_t>(fs::file_size(f.path, ec));
    files->push_back(std::move(f));
  }
  return true;
}

std::vector<std::string> KeepDicomFiles(std::vector<InputFile>* files) {
  std::vector<std::string> dropped;
  std::vector<InputFile> kept;
  for (auto& f : *files) {
    bool dicom = false;
    if (AsciiLower(f.path.filename().string()) != "dicomdir") {
      std::ifstream in(f.path, std::ios::binary);
      char magic[132] = {};
      dicom = in.read(magic, sizeof magic) && std::string(magic + 128, 4) == "DICM";
    }
    if (dicom) {
      kept.push_back(std::move(f));
    } else {
      dropped.push_back(f.name);
    }
  }
  *files = std::move(kept);
  return dropped;
}

namespace {
// Seconds of each stage of the CT head job (128x128x53, 4.2 M cells, field policy, 50 %, one
// 512 px view) at the commit that added this table; the MRI demo has the same order of shares.
struct StageWeight {
  const char* stage;
  double seconds;
};
// "curve" (only when asked for: 10 % steps of extra simplifications and renders) measured 2.8x
// the job's own simplify on the same CT job.
constexpr StageWeight kStageWeights[] = {{"load", 0.03},     {"segment", 2.24}, {"tetra", 1.74},
                                         {"simplify", 14.8}, {"write", 0.85},   {"render", 7.16},
                                         {"curve", 41.4},    {"diff", 0.05}};
}  // namespace

bool JobWithCurve(const v1::Job& job) {
  for (const auto& o : job.spec().outputs()) {
    if (o == "curve") return true;
  }
  return false;
}

double OverallFraction(const std::string& stage, double stage_fraction, bool with_curve) {
  double total = 0, before = 0, own = 0;
  bool found = false;
  for (const auto& w : kStageWeights) {
    if (!with_curve && std::string_view(w.stage) == "curve") continue;
    if (stage == w.stage) {
      found = true;
      own = w.seconds;
    } else if (!found) {
      before += w.seconds;
    }
    total += w.seconds;
  }
  if (!found) return 0;
  return std::clamp((before + own * std::clamp(stage_fraction, 0.0, 1.0)) / total, 0.0, 1.0);
}

std::string FormatDuration(double seconds) {
  if (!(seconds >= 0)) return "-";
  const long long s = static_cast<long long>(seconds + 0.5);
  char buf[32];
  if (s >= 3600) {
    std::snprintf(buf, sizeof buf, "%lld:%02lld:%02lld", s / 3600, s / 60 % 60, s % 60);
  } else {
    std::snprintf(buf, sizeof buf, "%lld:%02lld", s / 60, s % 60);
  }
  return buf;
}

std::string FormatBytes(int64_t bytes) {
  char buf[32];
  if (bytes >= 1000 * 1000 * 1000) {
    std::snprintf(buf, sizeof buf, "%.2f GB", bytes / 1e9);
  } else if (bytes >= 1000 * 1000) {
    std::snprintf(buf, sizeof buf, "%.1f MB", bytes / 1e6);
  } else if (bytes >= 1000) {
    std::snprintf(buf, sizeof buf, "%.0f KB", bytes / 1e3);
  } else {
    std::snprintf(buf, sizeof buf, "%lld B", static_cast<long long>(bytes));
  }
  return buf;
}

double JobFraction(const v1::Progress& p, bool with_curve) {
  if (p.has_overall_fraction()) return std::clamp(p.overall_fraction(), 0.0, 1.0);
  return OverallFraction(p.stage(), p.fraction(), with_curve);
}

std::string OverallBar(const v1::Progress& p, double elapsed_s, int width, bool with_curve,
                       double since_event_s) {
  const double f = JobFraction(p, with_curve);
  const int filled = static_cast<int>(f * width + 0.5);
  std::string bar(static_cast<size_t>(filled), '#');
  bar.append(static_cast<size_t>(width - filled), '.');
  char head[64];
  std::snprintf(head, sizeof head, "[%s] %3d%% ", bar.c_str(), static_cast<int>(f * 100));
  std::string out = head;
  out += p.stage() + " " + std::to_string(static_cast<int>(p.fraction() * 100)) + "%";
  out += "  elapsed " + FormatDuration(elapsed_s);
  if (p.has_eta_seconds()) {
    if (f < 1) out += "  ETA " + FormatDuration(std::max(0.0, p.eta_seconds() - since_event_s));
  } else if (f >= 0.02 && f < 1) {
    out += "  ETA " + FormatDuration(elapsed_s * (1 - f) / f);
  }
  return out;
}

// Where the value of "key" starts in metrics.json (its first character after the colon), or
// npos if the key is absent. metrics.json is ours; its few fields the client shows are found by
// plain string search, so the client keeps depending on the proto library only.
static size_t MetricsValueAt(const std::string& m, const std::string& key) {
  size_t at = m.find("\"" + key + "\"");
  if (at == std::string::npos) return at;
  at = m.find(':', at);
  return at == std::string::npos ? at : m.find_first_not_of(" \t\n\r", at + 1);
}

std::vector<std::string> FidelityLines(const std::string& m) {
  auto value_at = [&](const std::string& key) { return MetricsValueAt(m, key); };
  std::vector<std::string> lines;
  for (const char* key : {"diff1", "psnr_db", "mean_dice"}) {
    const size_t at = value_at(key);
    if (at == std::string::npos) continue;
    if (m.compare(at, 4, "null") == 0) {
      const size_t rmse = value_at("rmse");
      const bool exact = rmse != std::string::npos && m.compare(rmse, 4, "null") != 0 &&
                         std::strtod(m.c_str() + rmse, nullptr) == 0;
      lines.push_back(std::string(key) + (exact ? " inf (rmse 0)" : " n/a"));
      continue;
    }
    char figure[64];
    std::snprintf(figure, sizeof figure, "%s %g", key, std::strtod(m.c_str() + at, nullptr));
    lines.push_back(figure);
  }
  return lines;
}

JobSummary SummarizeJob(const v1::Job& job, int64_t input_bytes) {
  JobSummary s;
  s.input_bytes = input_bytes;
  for (const auto& a : job.artifacts()) s.artifact_bytes += a.size_bytes();
  s.target_reduction = job.spec().target_reduction();
  const std::string& m = job.metrics_json();
  auto number = [&](const std::string& key, double* out) {
    const size_t at = MetricsValueAt(m, key);
    if (at != std::string::npos) *out = std::strtod(m.c_str() + at, nullptr);
  };
  double before = 0, after = 0;
  number("achieved_reduction", &s.achieved_reduction);
  number("cells_before", &before);
  number("cells_after", &after);
  s.cells_before = static_cast<int64_t>(before);
  s.cells_after = static_cast<int64_t>(after);
  size_t at = m.find("\"reached_target\"");
  if (at != std::string::npos) {
    size_t v = m.find_first_not_of(" :", at + 16);
    s.reached_target = v == std::string::npos || m.compare(v, 5, "false") != 0;
  }
  at = m.find("\"stop_reason\"");
  if (at != std::string::npos) {
    const size_t v = m.find('"', m.find(':', at) + 1);
    s.stopped_by_floor = v != std::string::npos && m.compare(v, 10, "\"min_psnr\"") == 0;
  }
  at = m.find("\"stop_message\"");
  if (at != std::string::npos) {
    size_t q = m.find('"', m.find(':', at) + 1);
    size_t e = q == std::string::npos ? q : m.find('"', q + 1);
    if (e != std::string::npos) s.stop_message = m.substr(q + 1, e - q - 1);
  }
  return s;
}

std::vector<std::string> SummaryLines(const JobSummary& s) {
  std::vector<std::string> out;
  char buf[512];
  std::snprintf(buf, sizeof buf,
                "reduction: %.1f%% of the cells removed (target %.1f%%), %lld -> %lld cells",
                100 * s.achieved_reduction, 100 * s.target_reduction,
                static_cast<long long>(s.cells_before), static_cast<long long>(s.cells_after));
  out.push_back(buf);
  std::string sizes = "sizes: artifacts " + FormatBytes(s.artifact_bytes);
  if (s.input_bytes > 0) {
    std::snprintf(buf, sizeof buf, " for %s of input (%.1fx the input's bytes)",
                  FormatBytes(s.input_bytes).c_str(),
                  static_cast<double>(s.artifact_bytes) / static_cast<double>(s.input_bytes));
    sizes += buf;
  }
  out.push_back(sizes);
  if (s.stopped_by_floor) {
    out.push_back("stopped by the PSNR floor: " + s.stop_message);
  } else if (!s.reached_target) {
    out.push_back("WARNING: the reduction target was not reached (" + s.stop_message +
                  "); exit code 10");
  }
  return out;
}

bool ParseJobState(const std::string& name, v1::JobState* state) {
  std::string upper = name;
  for (char& c : upper) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  v1::JobState v;
  if (!v1::JobState_Parse(upper, &v) || v == v1::JOB_STATE_UNSPECIFIED) return false;
  *state = v;
  return true;
}

}  // namespace decima::client
