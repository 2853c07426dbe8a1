// The job lifecycle rules on their own, without a store: each transition's state, counters and
// the one event it appends. Both stores run them (job_store_test.cc checks the stores' history).
#include "server/store/job_lifecycle.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <string>

namespace decima::server {
namespace {

v1::Job JobIn(v1::JobState state, int attempts) {
  v1::Job job;
  job.set_name("jobs/j1");
  job.set_state(state);
  job.set_attempts(attempts);
  job.set_last_sequence(4);
  return job;
}

// The one state-change event a transition appended, checked for its number and job.
v1::JobState OnlyStateEvent(const PendingEvents& events) {
  EXPECT_EQ(events.size(), 1u);
  if (events.size() != 1) return v1::JOB_STATE_UNSPECIFIED;
  EXPECT_EQ(events[0].first, "j1");
  EXPECT_EQ(events[0].second.sequence(), 5);
  EXPECT_TRUE(events[0].second.has_time());
  return events[0].second.state_change().state();
}

TEST(JobLifecycle, ANewJobIsQueuedWithItsSpecCreatorAndFirstEvent) {
  v1::JobSpec spec;
  spec.set_volume("volumes/v1");
  PendingEvents events;
  v1::Job job = NewQueuedJob("j9", spec, "req-1", "alice", &events);
  EXPECT_EQ(job.name(), "jobs/j9");
  EXPECT_EQ(job.state(), v1::QUEUED);
  EXPECT_EQ(job.spec().volume(), "volumes/v1");
  EXPECT_EQ(job.request_id(), "req-1");
  EXPECT_EQ(job.creator(), "alice");
  EXPECT_TRUE(job.has_create_time());
  ASSERT_EQ(events.size(), 1u);
  EXPECT_EQ(events[0].first, "j9");
  EXPECT_EQ(events[0].second.sequence(), 1);
  EXPECT_EQ(events[0].second.state_change().state(), v1::QUEUED);
}

TEST(JobLifecycle, StartAttemptCountsTheClaimAndClearsThePreviousAttempt) {
  v1::Job job = JobIn(v1::QUEUED, 1);
  job.mutable_error()->set_message("old");
  job.mutable_progress()->set_fraction(0.5);
  job.mutable_end_time()->set_seconds(7);
  PendingEvents events;
  StartAttempt(job, &events);
  EXPECT_EQ(job.state(), v1::RUNNING);
  EXPECT_EQ(job.attempts(), 2);
  EXPECT_FALSE(job.has_error());
  EXPECT_FALSE(job.has_progress());
  EXPECT_FALSE(job.has_end_time());
  EXPECT_TRUE(job.has_start_time());
  EXPECT_EQ(OnlyStateEvent(events), v1::RUNNING);
  EXPECT_EQ(job.last_sequence(), 5);
}

TEST(JobLifecycle, RequeueAtShutdownGivesTheAttemptBack) {
  v1::Job job = JobIn(v1::RUNNING, 1);
  PendingEvents events;
  RequeueAttempt(job, "server draining", &events);
  EXPECT_EQ(job.state(), v1::QUEUED);
  EXPECT_EQ(job.attempts(), 0);
  EXPECT_EQ(job.progress().message(), "server draining");
  EXPECT_EQ(OnlyStateEvent(events), v1::QUEUED);
}

TEST(JobLifecycle, FinishKeepsTheOutcomesErrorArtifactsAndMetrics) {
  v1::Job job = JobIn(v1::RUNNING, 1);
  v1::Job outcome;
  outcome.mutable_error()->set_message("segmentation failed");
  outcome.set_metrics_json("{}");
  PendingEvents events;
  FinishAttempt(job, v1::FAILED, outcome, &events);
  EXPECT_EQ(job.state(), v1::FAILED);
  EXPECT_EQ(job.error().message(), "segmentation failed");
  EXPECT_EQ(job.metrics_json(), "{}");
  EXPECT_TRUE(job.has_end_time());
  EXPECT_EQ(OnlyStateEvent(events), v1::FAILED);
  EXPECT_EQ(events[0].second.state_change().error().message(), "segmentation failed");
}

TEST(JobLifecycle, ALapsedLeaseCancelsFailsOrRequeuesInThatOrder) {
  {
    v1::Job job = JobIn(v1::RUNNING, 3);
    PendingEvents events;
    EXPECT_EQ(ResolveLapsedLease(job, /*cancel_requested=*/true, 3, &events),
              LapsedLease::kCancelled);
    EXPECT_EQ(job.state(), v1::CANCELLED);
    EXPECT_EQ(OnlyStateEvent(events), v1::CANCELLED);
  }
  {
    v1::Job job = JobIn(v1::RUNNING, 3);
    PendingEvents events;
    EXPECT_EQ(ResolveLapsedLease(job, false, 3, &events), LapsedLease::kFailed);
    EXPECT_EQ(job.state(), v1::FAILED);
    EXPECT_EQ(job.error().code(), static_cast<int>(absl::StatusCode::kUnavailable));
    EXPECT_NE(job.error().message().find("lost 3 times"), std::string::npos);
    EXPECT_EQ(OnlyStateEvent(events), v1::FAILED);
  }
  {
    v1::Job job = JobIn(v1::RUNNING, 2);
    PendingEvents events;
    EXPECT_EQ(ResolveLapsedLease(job, false, 3, &events), LapsedLease::kRequeued);
    EXPECT_EQ(job.state(), v1::QUEUED);
    EXPECT_EQ(job.attempts(), 2);  // a lost worker's attempt counts
    EXPECT_EQ(OnlyStateEvent(events), v1::QUEUED);
  }
}

TEST(JobLifecycle, OnlyFailedOrCancelledJobsAreRetriedAndOnlyFinalOnesDeleted) {
  for (v1::JobState s : {v1::QUEUED, v1::RUNNING, v1::SUCCEEDED}) {
    EXPECT_EQ(CheckRetryable(JobIn(s, 1)).code(), absl::StatusCode::kFailedPrecondition) << s;
  }
  EXPECT_TRUE(CheckRetryable(JobIn(v1::FAILED, 1)).ok());
  EXPECT_TRUE(CheckRetryable(JobIn(v1::CANCELLED, 1)).ok());
  EXPECT_EQ(CheckDeletable(JobIn(v1::RUNNING, 1)).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(CheckDeletable(JobIn(v1::SUCCEEDED, 1)).ok());
  EXPECT_EQ(CheckQueueRoom(5, 5).code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(CheckQueueRoom(5, 5).message().find("5 jobs queued, --max-queued 5"),
            std::string::npos);
  EXPECT_TRUE(CheckQueueRoom(4, 5).ok());
  EXPECT_TRUE(CheckQueueRoom(1000000, 0).ok());

  v1::Job job = JobIn(v1::FAILED, 3);
  job.mutable_error()->set_message("x");
  job.set_metrics_json("{}");
  PendingEvents events;
  ResetForRetry(job, &events);
  EXPECT_EQ(job.state(), v1::QUEUED);
  EXPECT_EQ(job.attempts(), 0);
  EXPECT_FALSE(job.has_error());
  EXPECT_TRUE(job.metrics_json().empty());
  EXPECT_EQ(OnlyStateEvent(events), v1::QUEUED);
}

TEST(JobLifecycle, PageTokensRoundTripAndForeignTokensAreRefused) {
  EXPECT_EQ(*DecodePageToken(EncodePageToken(42)), 42);
  EXPECT_EQ(*DecodePageToken(""), INT64_MAX);
  for (const char* bad : {"o", "x5", "o-1", "o12a"}) {
    EXPECT_EQ(DecodePageToken(bad).status().code(), absl::StatusCode::kInvalidArgument) << bad;
  }
  EXPECT_EQ(ClampPageSize(0), 50);
  EXPECT_EQ(ClampPageSize(5000), 1000);
  EXPECT_EQ(ClampPageSize(7), 7);
}

}  // namespace
}  // namespace decima::server
