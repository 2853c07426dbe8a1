// The rules of a job's lifecycle, written once as pure functions on v1::Job. Both job stores
// (SQLite and PostgreSQL) call them inside their own transaction and then persist the job and
// the events these functions append; the stores own only the SQL (which rows, which locks).
//
// Invariants kept here:
// - every change of state appends exactly one state-change event, numbered after the job's
//   last_sequence, so watchers of either store see the same history;
// - `attempts` counts claims: a claim adds one, a requeue at shutdown gives it back (the attempt
//   did not fail), a retry by request starts again from zero.
#ifndef DECIMA_SERVER_JOB_LIFECYCLE_H_
#define DECIMA_SERVER_JOB_LIFECYCLE_H_

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "decima/v1/jobs.pb.h"

namespace decima::server {

// Events a transaction appended, as (job id, event), in order; the store writes them with the job.
using PendingEvents = std::vector<std::pair<std::string, v1::JobEvent>>;

// The id of `job` ("jobs/{id}" -> "{id}").
std::string JobIdOf(const v1::Job& job);

// Gives `ev` the job's next sequence number and the current time, and appends it to `events`.
void AppendEvent(v1::Job& job, v1::JobEvent ev, PendingEvents* events);
// Appends a state-change event to `state`, with `error` when it is not null.
void AppendStateEvent(v1::Job& job, v1::JobState state, const v1::JobError* error,
                      PendingEvents* events);

// A new job `id` of `creator`, QUEUED with `spec` (already normalized) and its request id.
v1::Job NewQueuedJob(const std::string& id, const v1::JobSpec& spec, const std::string& request_id,
                     const std::string& creator, PendingEvents* events);
// A worker claimed the job: RUNNING, one more attempt, a new start time, the previous attempt's
// end time, error and progress cleared.
void StartAttempt(v1::Job& job, PendingEvents* events);
// The worker reported progress.
void RecordProgress(v1::Job& job, const v1::Progress& progress, PendingEvents* events);
// The worker finished with `state`; the outcome's error, artifacts and metrics are kept.
void FinishAttempt(v1::Job& job, v1::JobState state, const v1::Job& outcome, PendingEvents* events);
// The worker gave the job back (shutdown): QUEUED again, the attempt not counted, `reason` shown
// as its progress message.
void RequeueAttempt(v1::Job& job, const std::string& reason, PendingEvents* events);

// What happened to a RUNNING job whose worker's lease lapsed.
enum class LapsedLease { kCancelled, kFailed, kRequeued };
// A cancel was requested: CANCELLED. Else after `max_attempts` claims: FAILED (UNAVAILABLE).
// Else QUEUED for another worker.
LapsedLease ResolveLapsedLease(v1::Job& job, bool cancel_requested, int max_attempts,
                               PendingEvents* events);

// Cancels a QUEUED job at once (a RUNNING one is cancelled by its worker, not here).
void CancelQueued(v1::Job& job, PendingEvents* events);

// OK when `job` may be retried (FAILED or CANCELLED), else FAILED_PRECONDITION naming its state.
absl::Status CheckRetryable(const v1::Job& job);
// OK while `queued` jobs leave room under `max_queued` (0 = no limit), else RESOURCE_EXHAUSTED.
absl::Status CheckQueueRoom(int64_t queued, int max_queued);
// A retry by request: QUEUED from scratch (attempts, error, artifacts, metrics, times cleared).
void ResetForRetry(v1::Job& job, PendingEvents* events);
// OK when `job` is in a final state, else FAILED_PRECONDITION (cancel it first).
absl::Status CheckDeletable(const v1::Job& job);

// Page tokens of the job and volume listings: "o" + the row's order number; "" is the first page.
std::string EncodePageToken(int64_t ord);
// The order number below which the next page starts (INT64_MAX for ""), or INVALID_ARGUMENT.
absl::StatusOr<int64_t> DecodePageToken(const std::string& token);
// 50 when unset (<= 0), at most 1000.
int ClampPageSize(int page_size);

}  // namespace decima::server

#endif  // DECIMA_SERVER_JOB_LIFECYCLE_H_
