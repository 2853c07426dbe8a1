// `decima watch`: one job with its progress bar and end-of-job summary, or several at once
// with a line per stage and one table. Both follow each job with a JobEventStream.
#pragma once

#include <string>
#include <vector>

#include "client/cli/context.h"
#include "client/cli/output.h"

namespace decima::client {

// Watches a job until a final state, reconnecting with the last sequence while the server
// restarts. Returns the exit code and the final job in *final.
int Watch(CliContext& ctx, const std::string& name, v1::Job* final);

// How one of several watched jobs ended.
struct WatchOutcome {
  v1::Job final;
  int rc = kError;    // 0, kJobFailed, kJobCancelled, kTargetNotReached, or the watch's error
  std::string error;  // the watch's own failure ("UNAVAILABLE: ..."), else ""
};

// Follows several jobs at once: one thread and one stream per job, all printing plain lines
// prefixed with the job id, one line at a time. With --json the events go to stdout as JSON
// lines (each names its job). Returns when every job is final (or its watch failed); outcomes
// in the order of `names`.
std::vector<WatchOutcome> WatchMany(CliContext& ctx, const std::vector<std::string>& names);

// A finished job's row: the state, and what a user wants next to it (the achieved reduction,
// or why it failed).
void SetOutcome(const WatchOutcome& o, StudyRow* row);

}  // namespace decima::client
