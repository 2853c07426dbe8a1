#include "server/store/job_lifecycle.h"

#include <algorithm>
#include <cstdint>
#include <utility>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "server/store/job_store.h"

namespace decima::server {

std::string JobIdOf(const v1::Job& job) { return job.name().substr(5); }

void AppendEvent(v1::Job& job, v1::JobEvent ev, PendingEvents* events) {
  job.set_last_sequence(job.last_sequence() + 1);
  ev.set_sequence(job.last_sequence());
  *ev.mutable_time() = NowTimestamp();
  events->emplace_back(JobIdOf(job), std::move(ev));
}

void AppendStateEvent(v1::Job& job, v1::JobState state, const v1::JobError* error,
                      PendingEvents* events) {
  v1::JobEvent ev;
  ev.mutable_state_change()->set_state(state);
  if (error != nullptr) *ev.mutable_state_change()->mutable_error() = *error;
  AppendEvent(job, std::move(ev), events);
}

namespace {

// Ends the job in `state` with `code` and `message` as its error, now.
void EndWithError(v1::Job& job, v1::JobState state, absl::StatusCode code,
                  const std::string& message, PendingEvents* events) {
  job.set_state(state);
  job.mutable_error()->set_code(static_cast<int>(code));
  job.mutable_error()->set_message(message);
  *job.mutable_end_time() = NowTimestamp();
  AppendStateEvent(job, state, &job.error(), events);
}

}  // namespace

void StartAttempt(v1::Job& job, PendingEvents* events) {
  job.set_state(v1::RUNNING);
  job.set_attempts(job.attempts() + 1);
  *job.mutable_start_time() = NowTimestamp();
  job.clear_end_time();
  job.clear_error();
  job.clear_progress();
  AppendStateEvent(job, v1::RUNNING, nullptr, events);
}

void RecordProgress(v1::Job& job, const v1::Progress& progress, PendingEvents* events) {
  *job.mutable_progress() = progress;
  v1::JobEvent ev;
  *ev.mutable_progress() = progress;
  AppendEvent(job, std::move(ev), events);
}

void FinishAttempt(v1::Job& job, v1::JobState state, const v1::Job& outcome,
                   PendingEvents* events) {
  job.set_state(state);
  *job.mutable_end_time() = NowTimestamp();
  if (outcome.has_error()) *job.mutable_error() = outcome.error();
  *job.mutable_artifacts() = outcome.artifacts();
  job.set_metrics_json(outcome.metrics_json());
  AppendStateEvent(job, state, outcome.has_error() ? &outcome.error() : nullptr, events);
}

void RequeueAttempt(v1::Job& job, const std::string& reason, PendingEvents* events) {
  job.set_state(v1::QUEUED);
  job.set_attempts(std::max(0, job.attempts() - 1));
  job.mutable_progress()->set_message(reason);
  AppendStateEvent(job, v1::QUEUED, nullptr, events);
}

LapsedLease ResolveLapsedLease(v1::Job& job, bool cancel_requested, int max_attempts,
                               PendingEvents* events) {
  if (cancel_requested) {
    EndWithError(job, v1::CANCELLED, absl::StatusCode::kCancelled,
                 "cancelled by request (its worker was lost)", events);
    return LapsedLease::kCancelled;
  }
  if (job.attempts() >= max_attempts) {
    EndWithError(
        job, v1::FAILED, absl::StatusCode::kUnavailable,
        absl::StrCat("the worker was lost ", job.attempts(), " times (lease lapsed); giving up"),
        events);
    return LapsedLease::kFailed;
  }
  job.set_state(v1::QUEUED);
  job.mutable_progress()->set_message("requeued: the lease of its worker lapsed");
  AppendStateEvent(job, v1::QUEUED, nullptr, events);
  return LapsedLease::kRequeued;
}

void CancelQueued(v1::Job& job, PendingEvents* events) {
  EndWithError(job, v1::CANCELLED, absl::StatusCode::kCancelled,
               "cancelled by request while queued", events);
}

absl::Status CheckRetryable(const v1::Job& job) {
  if (job.state() == v1::FAILED || job.state() == v1::CANCELLED) return absl::OkStatus();
  return absl::FailedPreconditionError(
      absl::StrCat("job ", JobIdOf(job), " is ", v1::JobState_Name(job.state()),
                   "; only FAILED or CANCELLED jobs can be retried"));
}

absl::Status CheckQueueRoom(int64_t queued, int max_queued) {
  if (max_queued <= 0 || queued < max_queued) return absl::OkStatus();
  return absl::ResourceExhaustedError(absl::StrCat(
      "the queue is full (", queued, " jobs queued, --max-queued ", max_queued, "); retry later"));
}

v1::Job NewQueuedJob(const std::string& id, const v1::JobSpec& spec, const std::string& request_id,
                     const std::string& creator, PendingEvents* events) {
  v1::Job job;
  job.set_name(absl::StrCat("jobs/", id));
  *job.mutable_spec() = spec;
  job.set_state(v1::QUEUED);
  job.set_request_id(request_id);
  job.set_creator(creator);
  *job.mutable_create_time() = NowTimestamp();
  AppendStateEvent(job, v1::QUEUED, nullptr, events);
  return job;
}

void ResetForRetry(v1::Job& job, PendingEvents* events) {
  job.set_state(v1::QUEUED);
  job.set_attempts(0);
  job.clear_error();
  job.clear_artifacts();
  job.clear_metrics_json();
  job.clear_progress();
  job.clear_start_time();
  job.clear_end_time();
  AppendStateEvent(job, v1::QUEUED, nullptr, events);
}

absl::Status CheckDeletable(const v1::Job& job) {
  if (IsFinal(job.state())) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      "job ", JobIdOf(job), " is ", v1::JobState_Name(job.state()), "; cancel it before deleting"));
}

std::string EncodePageToken(int64_t ord) { return absl::StrCat("o", ord); }

absl::StatusOr<int64_t> DecodePageToken(const std::string& token) {
  if (token.empty()) return INT64_MAX;
  int64_t v = 0;
  if (token.size() < 2 || token[0] != 'o' || !absl::SimpleAtoi(token.substr(1), &v) || v < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_token '", token, "' is not a token this server returned"));
  }
  return v;
}

int ClampPageSize(int page_size) {
  if (page_size <= 0) return 50;
  return page_size > 1000 ? 1000 : page_size;
}

}  // namespace decima::server
