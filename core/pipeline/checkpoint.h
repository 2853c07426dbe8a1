// Stage checkpoints of one job: the output of a finished expensive stage (the segmentation after
// "segment", the simplified mesh after "simplify") saved in a folder that outlives the job
// process, so that a requeued attempt resumes from the last finished stage instead of from zero.
//
// A checkpoint file is trusted only when it is complete and intact and was made from the same
// inputs: it is written to a temporary name, fsynced and renamed (a crash leaves the old file or
// none, never a torn one), and holds the caller's key (what the stage's output depends on: the
// server passes the volume's sha256 and the normalized job spec) and the sha256 of its payload.
// A file with another key, a bad checksum or a payload that does not parse is ignored (the stage
// runs again). The payload is lossless binary (floats as their bits), so a resumed job produces
// byte-identical outputs.
//
// File layout: "DECIMA-CHECKPOINT 1\n", key length (u64) and key, payload length (u64),
// 64 hex characters of the payload's sha256, payload. Integers little-endian (the machine's; a
// checkpoint is read back on the same architecture, and a mismatch only fails the checksum or
// the parse, i.e. the stage runs again).
#pragma once

#include <filesystem>
#include <functional>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/byte_record.h"
#include "core/segment/segment.h"
#include "core/simplify/simplify.h"

namespace decima::pipeline {

// Lower-case hex sha256 of `bytes` (core/common Sha256).
std::string Sha256Hex(std::string_view bytes);

// Serialization of the two checkpointed stage outputs: Put* write it into a ByteWriter (to a file
// by the WriteCheckpoint below, with no copy in memory), Serialize* into a string. Parse* return
// InvalidArgument naming the field that is truncated or out of range; they never read past
// `bytes`.
std::string SerializeSegmentResult(const SegmentResult& seg);
void PutSegmentResult(ByteWriter& w, const SegmentResult& seg);
absl::StatusOr<SegmentResult> ParseSegmentResult(const std::string& bytes);
std::string SerializeSimplifyResult(const SimplifyResult& s);
void PutSimplifyResult(ByteWriter& w, const SimplifyResult& s);
absl::StatusOr<SimplifyResult> ParseSimplifyResult(const std::string& bytes);

// Writes `payload` under `key` to `path` atomically (temp file, fsync, rename, fsync of the
// folder). Internal error naming the file on failure.
absl::Status WriteCheckpoint(const std::filesystem::path& path, const std::string& key,
                             const std::string& payload);
// The same with the payload that `fill` writes into the writer it gets, which hands it to the
// file as it comes (its length and checksum are filled in after it): a payload of hundreds of MB
// (a clinical scan's simplified mesh) is never held in memory. The file is byte for byte the one
// the string version writes.
absl::Status WriteCheckpoint(const std::filesystem::path& path, const std::string& key,
                             const std::function<void(ByteWriter&)>& fill);

// The payload of `path` if it exists, is intact and was written under `key`; NotFound if there
// is no file, FailedPrecondition (saying why) for another key, a bad checksum or a torn file.
absl::StatusOr<std::string> ReadCheckpoint(const std::filesystem::path& path,
                                           const std::string& key);

}  // namespace decima::pipeline
