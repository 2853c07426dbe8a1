#include "server/files/volume_catalog.h"

#include <algorithm>
#include <set>
#include <utility>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "decima/v1/errors.pb.h"
#include "server/files/volume_probe.h"
#include "server/util/ids.h"
#include "server/util/sha256.h"

namespace decima::server {
namespace fs = std::filesystem;

bool SafeRelativePath(const std::string& p) {
  if (p.empty() || p.size() > 512 || p[0] == '/') return false;
  for (char c : p) {
    if (static_cast<unsigned char>(c) < 0x20 || c == '\\') return false;
  }
  for (absl::string_view part : absl::StrSplit(p, '/')) {
    if (part.empty() || part == "." || part == "..") return false;
  }
  return true;
}

std::string VolumeContentKey(const v1::Volume& volume) {
  std::vector<std::pair<std::string, std::string>> files;
  for (const auto& f : volume.files()) files.emplace_back(f.path(), f.blob());
  std::sort(files.begin(), files.end());
  // Length-prefixed fields: no choice of names can make two different manifests hash alike.
  std::string text =
      absl::StrCat("decima-volume-content-1\n", volume.format(), "\n",
                   volume.series_instance_uid().size(), ":", volume.series_instance_uid(), "\n");
  for (const auto& [path, blob] : files) {
    absl::StrAppend(&text, path.size(), ":", path, blob.size(), ":", blob, "\n");
  }
  Sha256 h;
  h.Update(text.data(), text.size());
  return h.HexDigest();
}

absl::StatusOr<v1::Volume> VolumeCatalog::Create(const v1::CreateVolumeRequest& request,
                                                 const std::string& creator,
                                                 v1::ErrorDetail* detail) {
  v1::Volume vol = request.volume();
  auto invalid = [&](const std::string& field, const std::string& message) {
    detail->set_field(field);
    return absl::InvalidArgumentError(absl::StrCat(field, ": ", message));
  };
  if (vol.files().empty()) return invalid("volume.files", "at least one file needed");
  if (vol.files_size() > 100000) return invalid("volume.files", "too many files");
  std::set<std::string> seen;
  std::vector<std::string> paths;
  std::vector<fs::path> sources;
  int64_t total = 0;
  for (int i = 0; i < vol.files_size(); ++i) {
    const auto& f = vol.files(i);
    const std::string field = absl::StrCat("volume.files[", i, "]");
    if (!SafeRelativePath(f.path())) {
      return invalid(field + ".path",
                     absl::StrCat("'", f.path(), "' is not a safe relative file name"));
    }
    if (!seen.insert(f.path()).second) {
      return invalid(field + ".path", absl::StrCat("'", f.path(), "' appears twice"));
    }
    auto sha = ParseName(f.blob(), "blobs", field + ".blob");
    if (!sha.ok() || !IsSha256Hex(*sha))
      return invalid(field + ".blob", "expected 'blobs/{sha256}'");
    auto path = blobs_->LocalPath(*sha);
    if (!path.ok()) {
      return absl::NotFoundError(absl::StrCat(field, ".blob: ", f.blob(), " was not uploaded"));
    }
    std::error_code ec;
    total += static_cast<int64_t>(fs::file_size(*path, ec));
    paths.push_back(f.path());
    sources.push_back(*path);
  }
  // A name that is also another file's folder ("s" and "s/IM2") cannot be materialized.
  for (size_t i = 0; i < paths.size(); ++i) {
    for (size_t slash = paths[i].find('/'); slash != std::string::npos;
         slash = paths[i].find('/', slash + 1)) {
      if (seen.count(paths[i].substr(0, slash))) {
        return invalid(absl::StrCat("volume.files[", i, "].path"),
                       absl::StrCat("'", paths[i], "' is inside '", paths[i].substr(0, slash),
                                    "', which is a file of the manifest"));
      }
    }
  }
  const std::string id = NewId();
  const fs::path dir = data_dir_->volume_files(id);
  // Materialize the files under their manifest names: hard links to the immutable blobs.
  for (size_t i = 0; i < paths.size(); ++i) {
    std::error_code ec;
    fs::create_directories((dir / paths[i]).parent_path(), ec);
    fs::create_hard_link(sources[i], dir / paths[i], ec);
    if (ec) {
      ec.clear();
      fs::copy_file(sources[i], dir / paths[i], ec);
    }
    if (ec) {
      data_dir_->RemoveVolume(id);
      return absl::InternalError(absl::StrCat("materializing ", paths[i], ": ", ec.message()));
    }
  }
  auto header = ProbeVolume(dir, paths, vol.format(), vol.series_instance_uid());
  if (!header.ok()) {
    data_dir_->RemoveVolume(id);
    const bool series = absl::StartsWith(header.status().message(), "series_instance_uid") ||
                        absl::StrContains(header.status().message(), "choose one with");
    detail->set_field(series ? "volume.series_instance_uid" : "volume.files");
    return header.status();
  }
  vol.set_name("volumes/" + id);
  vol.set_format(header->format);
  vol.clear_dims();
  vol.clear_spacing();
  if (header->parsed) {
    for (int i = 0; i < 3; ++i) {
      vol.add_dims(header->dims[i]);
      vol.add_spacing(header->spacing[i]);
    }
  }
  vol.set_modality(header->modality);
  vol.set_scalar_type(header->scalar_type);
  vol.set_size_bytes(total);
  vol.set_creator(creator);
  vol.clear_reused();  // output only: what a client sent is not stored
  *vol.mutable_create_time() = NowTimestamp();
  if (vol.display_name().empty()) vol.set_display_name(paths[0]);
  bool created = false;
  // Found by content after the probe, so the key holds the parsed format (a request naming it
  // and one leaving it to detection are the same content) and the store decides atomically.
  auto stored = jobs_->CreateVolume(id, vol, request.request_id(), VolumeContentKey(vol), &created);
  if (!stored.ok() || !created) data_dir_->RemoveVolume(id);
  if (stored.ok()) stored->set_reused(!created);
  return stored;
}

absl::Status VolumeCatalog::Delete(const std::string& id) {
  auto vol = jobs_->GetVolume(id);
  if (!vol.ok()) return vol.status();
  disk_->BeforeDelete();
  if (auto st = jobs_->DeleteVolume(id); !st.ok()) return st;
  data_dir_->RemoveVolume(id);
  std::vector<std::string> released;
  for (const auto& f : vol->files()) released.push_back(f.blob().substr(6));
  blobs_->Sweep(sweep_, InUse(), &released);
  return absl::OkStatus();
}

std::function<bool(const std::string&)> VolumeCatalog::InUse() const {
  // A store error keeps the blob: deleting too little is harmless, too much is data loss.
  return [jobs = jobs_](const std::string& sha) {
    auto used = jobs->BlobInUse(sha);
    return !used.ok() || *used;
  };
}

BlobSweepStats VolumeCatalog::CollectGarbage() { return blobs_->Sweep(sweep_, InUse()); }

}  // namespace decima::server
