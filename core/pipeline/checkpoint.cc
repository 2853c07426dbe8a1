#include "core/pipeline/checkpoint.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string_view>
#include <type_traits>

#include "absl/strings/str_cat.h"
#include "core/common/byte_record.h"
#include "core/common/sha256.h"

namespace decima::pipeline {
namespace {

constexpr char kMagic[] = "DECIMA-CHECKPOINT 1\n";
using Writer = ByteWriter;

// Errors say "checkpoint: field F is truncated".
class Reader : public ByteReader {
 public:
  explicit Reader(std::string_view in) : ByteReader(in, "checkpoint") {}
};

#define DECIMA_CK(expr)                           \
  do {                                            \
    if (auto _st = (expr); !_st.ok()) return _st; \
  } while (0)

void PutMesh(Writer& w, const TetMesh& m) {
  w.PutVector(m.positions);
  w.PutVector(m.scalars);
  w.PutVector(m.labels);
  w.PutVector(m.interface_distance);
  w.PutVector(m.vertex_flags);
  w.PutVector(m.tets);
  w.PutVector(m.cell_regions);
}

absl::Status GetMesh(Reader& r, TetMesh* m) {
  DECIMA_CK(r.GetVector("mesh.positions", &m->positions));
  DECIMA_CK(r.GetVector("mesh.scalars", &m->scalars));
  DECIMA_CK(r.GetVector("mesh.labels", &m->labels));
  DECIMA_CK(r.GetVector("mesh.interface_distance", &m->interface_distance));
  DECIMA_CK(r.GetVector("mesh.vertex_flags", &m->vertex_flags));
  DECIMA_CK(r.GetVector("mesh.tets", &m->tets));
  DECIMA_CK(r.GetVector("mesh.cell_regions", &m->cell_regions));
  const size_t n = m->scalars.size();
  if (m->positions.size() != 3 * n || m->labels.size() != n || m->interface_distance.size() != n ||
      m->vertex_flags.size() != n || m->tets.size() % 4 != 0 ||
      m->cell_regions.size() != m->tets.size() / 4) {
    return absl::InvalidArgumentError("checkpoint: mesh arrays disagree in length");
  }
  for (int32_t v : m->tets) {
    if (v < 0 || static_cast<size_t>(v) >= n) {
      return absl::InvalidArgumentError(
          absl::StrCat("checkpoint: mesh.tets names vertex ", v, " of ", n));
    }
  }
  return absl::OkStatus();
}

absl::Status Errno(const char* what, const std::filesystem::path& path) {
  return absl::InternalError(
      absl::StrCat("checkpoint: ", what, " ", path.string(), ": ", std::strerror(errno)));
}

// Writes all of `bytes` at the file's offset; false (errno set) on failure.
bool WriteAll(int fd, std::string_view bytes) {
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    done += static_cast<size_t>(n);
  }
  return true;
}

}  // namespace

std::string Sha256Hex(std::string_view bytes) {
  Sha256 sha;
  sha.Update(bytes.data(), bytes.size());
  return sha.HexDigest();
}

void PutSegmentResult(ByteWriter& w, const SegmentResult& seg) {
  const Volume& l = seg.labels;
  for (int64_t d : l.dims) w.Put(d);
  for (int i = 0; i < 3; ++i) w.Put(l.spacing[i]);
  for (int i = 0; i < 3; ++i) w.Put(l.origin[i]);
  for (int i = 0; i < 9; ++i) w.Put(l.direction.data()[i]);
  w.Put(static_cast<uint8_t>(l.type));
  w.PutVector(l.bytes);
  w.PutString(l.modality);
  w.PutVector(seg.interface_distance_voxels);
  w.PutVector(seg.interface_distance_mm);
  w.PutVector(seg.class_means);
  w.PutVector(seg.region_voxels);
  w.PutVector(seg.region_volumes_mm3);
  w.Put<int32_t>(seg.iterations);
  w.Put<uint8_t>(seg.converged);
  w.Put(seg.energy);
  w.Put(seg.within_class_sigma);
}

std::string SerializeSegmentResult(const SegmentResult& seg) {
  Writer w;
  PutSegmentResult(w, seg);
  return w.Take();
}

absl::StatusOr<SegmentResult> ParseSegmentResult(const std::string& bytes) {
  Reader r(bytes);
  SegmentResult seg;
  Volume& l = seg.labels;
  for (int64_t& d : l.dims) DECIMA_CK(r.Get("labels.dims", &d));
  for (int i = 0; i < 3; ++i) DECIMA_CK(r.Get("labels.spacing", &l.spacing[i]));
  for (int i = 0; i < 3; ++i) DECIMA_CK(r.Get("labels.origin", &l.origin[i]));
  for (int i = 0; i < 9; ++i) DECIMA_CK(r.Get("labels.direction", &l.direction.data()[i]));
  uint8_t type = 0;
  DECIMA_CK(r.Get("labels.type", &type));
  if (type != static_cast<uint8_t>(VoxelType::kUInt8)) {
    return absl::InvalidArgumentError(
        absl::StrCat("checkpoint: labels.type ", int(type), ", expected uint8"));
  }
  l.type = VoxelType::kUInt8;
  DECIMA_CK(r.GetVector("labels.bytes", &l.bytes));
  DECIMA_CK(r.GetString("labels.modality", &l.modality));
  DECIMA_CK(r.GetVector("interface_distance_voxels", &seg.interface_distance_voxels));
  DECIMA_CK(r.GetVector("interface_distance_mm", &seg.interface_distance_mm));
  DECIMA_CK(r.GetVector("class_means", &seg.class_means));
  DECIMA_CK(r.GetVector("region_voxels", &seg.region_voxels));
  DECIMA_CK(r.GetVector("region_volumes_mm3", &seg.region_volumes_mm3));
  int32_t iterations = 0;
  uint8_t converged = 0;
  DECIMA_CK(r.Get("iterations", &iterations));
  DECIMA_CK(r.Get("converged", &converged));
  DECIMA_CK(r.Get("energy", &seg.energy));
  DECIMA_CK(r.Get("within_class_sigma", &seg.within_class_sigma));
  DECIMA_CK(r.Done());
  seg.iterations = iterations;
  if (converged > 1) {
    // One encoding per value: a resumed job must see what was saved (the fuzz target's round
    // trip found a 0xff that read back as true and was written as 1).
    return absl::InvalidArgumentError(
        absl::StrCat("checkpoint: converged is ", int(converged), ", expected 0 or 1"));
  }
  seg.converged = converged != 0;
  for (int64_t d : l.dims) {
    if (d <= 0 || d > (int64_t{1} << 20)) {
      return absl::InvalidArgumentError(absl::StrCat("checkpoint: labels.dims has ", d));
    }
  }
  const uint64_t voxels = static_cast<uint64_t>(l.voxel_count());
  if (l.bytes.size() != voxels || seg.interface_distance_voxels.size() != voxels ||
      seg.interface_distance_mm.size() != voxels) {
    return absl::InvalidArgumentError(
        absl::StrCat("checkpoint: label and distance arrays do not match ", voxels, " voxels"));
  }
  return seg;
}

void PutSimplifyResult(ByteWriter& w, const SimplifyResult& s) {
  PutMesh(w, s.mesh);
  w.PutVector(s.vertex_map);
  w.Put(s.input_cells);
  w.Put(s.output_cells);
  w.Put(s.achieved_reduction);
  w.Put<uint8_t>(s.reached_target);
  w.Put(static_cast<uint8_t>(s.stop_reason));
  w.PutString(s.stop_message);
  w.Put<int32_t>(s.passes);
  w.Put(s.collapses);
  w.Put(s.max_error);
  w.PutVector(s.pass_stats);
}

std::string SerializeSimplifyResult(const SimplifyResult& s) {
  Writer w;
  PutSimplifyResult(w, s);
  return w.Take();
}

absl::StatusOr<SimplifyResult> ParseSimplifyResult(const std::string& bytes) {
  Reader r(bytes);
  SimplifyResult s;
  DECIMA_CK(GetMesh(r, &s.mesh));
  DECIMA_CK(r.GetVector("vertex_map", &s.vertex_map));
  DECIMA_CK(r.Get("input_cells", &s.input_cells));
  DECIMA_CK(r.Get("output_cells", &s.output_cells));
  DECIMA_CK(r.Get("achieved_reduction", &s.achieved_reduction));
  uint8_t reached = 0, reason = 0;
  int32_t passes = 0;
  DECIMA_CK(r.Get("reached_target", &reached));
  DECIMA_CK(r.Get("stop_reason", &reason));
  DECIMA_CK(r.GetString("stop_message", &s.stop_message));
  DECIMA_CK(r.Get("passes", &passes));
  DECIMA_CK(r.Get("collapses", &s.collapses));
  DECIMA_CK(r.Get("max_error", &s.max_error));
  DECIMA_CK(r.GetVector("pass_stats", &s.pass_stats));
  DECIMA_CK(r.Done());
  if (reached > 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("checkpoint: reached_target is ", int(reached), ", expected 0 or 1"));
  }
  if (reason > static_cast<uint8_t>(StopReason::kPsnrFloor)) {
    return absl::InvalidArgumentError(absl::StrCat("checkpoint: stop_reason ", int(reason)));
  }
  const int64_t n = s.mesh.vertex_count();
  for (int32_t v : s.vertex_map) {
    if (v < -1 || v >= n) {
      return absl::InvalidArgumentError(
          absl::StrCat("checkpoint: vertex_map names vertex ", v, " of ", n));
    }
  }
  s.reached_target = reached != 0;
  s.stop_reason = static_cast<StopReason>(reason);
  s.passes = passes;
  return s;
}

absl::Status WriteCheckpoint(const std::filesystem::path& path, const std::string& key,
                             const std::string& payload) {
  return WriteCheckpoint(path, key, [&](ByteWriter& w) { w.PutBytes(payload); });
}

absl::Status WriteCheckpoint(const std::filesystem::path& path, const std::string& key,
                             const std::function<void(ByteWriter&)>& fill) {
  std::error_code ec;
  std::filesystem::create_directories(path.parent_path(), ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("checkpoint: creating ", path.parent_path().string(), ": ", ec.message()));
  }
  // The header with the payload's length and checksum zeroed; both are written over once the
  // payload has gone by.
  Writer header;
  header.PutString(key);
  const std::string head_before_length = std::string(kMagic) + header.Take();
  const std::string head = head_before_length + std::string(sizeof(uint64_t) + 64, '\0');
  const std::filesystem::path tmp = path.string() + ".tmp";
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return Errno("creating", tmp);
  auto fail = [&](const char* what) {
    absl::Status st = Errno(what, tmp);
    ::close(fd);
    std::filesystem::remove(tmp, ec);
    return st;
  };
  if (!WriteAll(fd, head)) return fail("writing");
  Sha256 sha;
  uint64_t length = 0;
  bool written = true;
  int write_errno = 0;  // the failed write's, for the error (later calls may change errno)
  {
    ByteWriter payload([&](std::string_view bytes) {
      if (!written) return;
      sha.Update(bytes.data(), bytes.size());
      written = WriteAll(fd, bytes);
      if (!written) write_errno = errno;
      length += bytes.size();
    });
    fill(payload);
    payload.Flush();
  }
  if (!written) {
    errno = write_errno;
    return fail("writing");
  }
  Writer tail;
  tail.Put<uint64_t>(length);
  const std::string filled = tail.Take() + sha.HexDigest();
  if (::pwrite(fd, filled.data(), filled.size(), off_t(head_before_length.size())) !=
      ssize_t(filled.size())) {
    return fail("writing");
  }
  // The data must be on disk before the rename makes it the checkpoint: otherwise a power loss
  // could leave the new name with old or no blocks.
  if (::fsync(fd) != 0) return fail("syncing");
  ::close(fd);
  if (::rename(tmp.c_str(), path.c_str()) != 0) return Errno("renaming to", path);
  const int dir = ::open(path.parent_path().c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir >= 0) {
    ::fsync(dir);  // the rename itself; best effort (some file systems refuse)
    ::close(dir);
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> ReadCheckpoint(const std::filesystem::path& path,
                                           const std::string& key) {
  // One read into a buffer of the file's size, and no copy of the payload but the final move:
  // the simplified mesh of a scan is tens to hundreds of MB, read on the resume's critical path.
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return absl::NotFoundError(absl::StrCat("no checkpoint ", path.string()));
    return Errno("opening", path);
  }
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    absl::Status s = Errno("reading", path);
    ::close(fd);
    return s;
  }
  std::string file(static_cast<size_t>(st.st_size), '\0');
  size_t done = 0;
  while (done < file.size()) {
    const ssize_t n = ::read(fd, file.data() + done, file.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    done += static_cast<size_t>(n);
  }
  ::close(fd);
  file.resize(done);
  const auto refuse = [&](const std::string& why) {
    return absl::FailedPreconditionError(absl::StrCat(path.string(), ": ", why));
  };
  const size_t magic = sizeof kMagic - 1;
  if (file.compare(0, magic, kMagic) != 0) return refuse("not a checkpoint (bad magic)");
  const std::string_view rest = std::string_view(file).substr(magic);
  Reader r(rest);
  std::string stored_key;
  uint64_t size = 0;
  if (!r.GetString("key", &stored_key).ok() || !r.Get("size", &size).ok()) {
    return refuse("truncated header");
  }
  if (stored_key != key) return refuse("made from other inputs (key differs)");
  const size_t header = sizeof(uint64_t) + stored_key.size() + sizeof(uint64_t);
  if (rest.size() < header + 64 || rest.size() - header - 64 != size) {
    return refuse(absl::StrCat("payload of ",
                               rest.size() < header + 64 ? 0 : rest.size() - header - 64,
                               " bytes, the header says ", size));
  }
  const std::string_view sha = rest.substr(header, 64);
  if (Sha256Hex(rest.substr(header + 64)) != sha) {
    return refuse("checksum mismatch (damaged file)");
  }
  file.erase(0, magic + header + 64);
  return file;
}

}  // namespace decima::pipeline
