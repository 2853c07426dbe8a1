// SHA-256 of files for uploads that arrive in chunks and resume from a prefix already on disk
// (the incremental hasher is core/common's decima::Sha256).
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "core/common/sha256.h"

namespace decima::server {

// core/common's hasher and file reader, which the server's code names in server::.
using ::decima::HashFilePrefix;
using ::decima::Sha256;

// Hex sha256 of a whole file.
absl::StatusOr<std::string> Sha256OfFile(const std::filesystem::path& path);

// True for 64 lower-case hex characters.
bool IsSha256Hex(absl::string_view s);

}  // namespace decima::server
