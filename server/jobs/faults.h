// Test-only fault injection, kept out of the public API (as LevelDB's tests inject faults through
// an Env, never through the database interface). A test passes a fault to CreateJob in the
// request metadata `decima-test-fault`; only a server started with --allow-faults reads it, keeps
// it beside the job (jobs/<id>/fault, so it survives a restart) and hands it to the job child,
// which applies it. A production server never looks at the key.
//
// Faults, comma separated: "crash" aborts the job process once it started; "sleep:S" spends S
// seconds (0..3600) in a cancellable "prepare" stage reporting progress every 50 ms;
// "pause-after:STAGE" (segment or simplify) pauses the job right after that stage's checkpoint
// was saved (not when it was resumed), so a test can stop the server exactly at a stage boundary;
// "pause-after:simplify-window-N" right after a streamed simplify stage saved the record of its
// N-th window (counted from 1 across its passes, by the attempt that saves it).
#pragma once

#include <filesystem>
#include <string>

#include "absl/status/status.h"
#include "core/common/progress.h"

namespace decima::server {

inline constexpr char kFaultMetadataKey[] = "decima-test-fault";

// OK if `faults` parses, else INVALID_ARGUMENT naming the metadata key.
absl::Status ValidateFaults(const std::string& faults);

// Applies `faults` in the job child: sleeps (polling `cancel`, reporting through `progress`),
// then sets *crash for the caller to abort at the right moment. Cancelled if cancelled.
absl::Status ApplyFaults(const std::string& faults, const ProgressFn& progress,
                         const CancelToken& cancel, bool* crash);

// Longest pause of "pause-after:STAGE": a forgotten test job ends on its own.
inline constexpr double kMaxPauseSeconds = 600;

// Applies "pause-after:STAGE" in the job child when `stage`'s checkpoint was saved: reports
// under `stage` ("test fault: paused after the STAGE checkpoint", once a second) until `cancel`
// fires (Cancelled) or kMaxPauseSeconds passed (OK). OK at once for any other stage.
absl::Status PauseAfterCheckpoint(const std::string& faults, const std::string& stage,
                                  const ProgressFn& progress, const CancelToken& cancel);

}  // namespace decima::server
