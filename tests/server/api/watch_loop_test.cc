// WatchLoop over the real SQLite store and event bus: a snapshot, then every event in order
// with no gap, the end after the final state, resume from a sequence, heartbeats, and the ways
// a watch ends early (watcher gone, server draining).
#include "server/api/watch_loop.h"

#include <atomic>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

using ::testing::HasSubstr;
using namespace std::chrono_literals;

class WatchLoopTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto s = OpenSqliteJobStore((testing::MakeScratchDir("watch_loop") / "jobs.sqlite").string());
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = std::move(*s);
    store_->SetListener(
        [this](const std::string& id, const v1::JobEvent& ev) { bus_.Publish(id, ev); });
    v1::JobSpec spec;
    spec.set_volume("volumes/v");
    bool created = false;
    ASSERT_TRUE(store_->CreateJob("a", spec, "", 10, "", &created).ok());
  }
  // Claims "a", reports `n` progress events, then finishes it.
  void RunJob(int n, v1::JobState final_state = v1::SUCCEEDED) {
    auto claim = store_->ClaimNext("w", 60000);
    ASSERT_TRUE(claim.ok() && claim->has_value());
    for (int i = 0; i < n; ++i) {
      v1::Progress p;
      p.set_stage("segment");
      p.set_fraction((i + 1.0) / n);
      ASSERT_TRUE(store_->AppendProgress((*claim)->lease, p).ok());
      std::this_thread::sleep_for(2ms);
    }
    ASSERT_TRUE(store_->Finish((*claim)->lease, final_state, v1::Job()).ok());
  }
  WatchControls Collect(std::vector<v1::JobEvent>* out) {
    WatchControls c;
    c.send = [out](const v1::JobEvent& ev) {
      out->push_back(ev);
      return true;
    };
    return c;
  }

  EventBus bus_;
  std::unique_ptr<JobStore> store_;
};

std::vector<int64_t> Sequences(const std::vector<v1::JobEvent>& events) {
  std::vector<int64_t> out;
  for (const auto& e : events) {
    if (!e.has_snapshot() && !e.has_heartbeat()) out.push_back(e.sequence());
  }
  return out;
}

TEST_F(WatchLoopTest, StreamsEveryEventOfARunningJobInOrderAndEndsAfterTheFinalState) {
  std::vector<v1::JobEvent> got;
  WatchLoop loop(store_.get(), &bus_, WatchOptions{.heartbeat = 10s, .wait = 20ms});
  std::thread job([&] { RunJob(40); });
  const absl::Status st = loop.Run("a", 0, Collect(&got));
  job.join();
  ASSERT_TRUE(st.ok()) << st;
  ASSERT_FALSE(got.empty());
  EXPECT_TRUE(got.front().has_snapshot());
  const auto seqs = Sequences(got);
  ASSERT_EQ(seqs.size(), 43u);  // QUEUED, RUNNING, 40 progress, SUCCEEDED
  for (size_t i = 0; i < seqs.size(); ++i) EXPECT_EQ(seqs[i], static_cast<int64_t>(i + 1));
  EXPECT_EQ(got.back().state_change().state(), v1::SUCCEEDED);
}

TEST_F(WatchLoopTest, AFinishedJobIsOneSnapshotAndAResumeSendsOnlyWhatCameAfter) {
  RunJob(3);
  std::vector<v1::JobEvent> all, tail, none;
  WatchLoop loop(store_.get(), &bus_);
  ASSERT_TRUE(loop.Run("a", 0, Collect(&all)).ok());
  EXPECT_EQ(Sequences(all), (std::vector<int64_t>{1, 2, 3, 4, 5, 6}));
  ASSERT_TRUE(loop.Run("a", 4, Collect(&tail)).ok());
  EXPECT_EQ(Sequences(tail), (std::vector<int64_t>{5, 6}));
  ASSERT_TRUE(loop.Run("a", 6, Collect(&none)).ok());
  ASSERT_EQ(none.size(), 1u);
  EXPECT_TRUE(none[0].has_snapshot());
}

TEST_F(WatchLoopTest, HeartbeatsCarryTheLastSequenceWhileNothingHappens) {
  std::vector<v1::JobEvent> got;
  WatchControls c = Collect(&got);
  c.cancelled = [&] {
    int beats = 0;
    for (const auto& e : got) beats += e.has_heartbeat();
    return beats >= 2;
  };
  WatchLoop loop(store_.get(), &bus_, WatchOptions{.heartbeat = 30ms, .wait = 10ms});
  const absl::Status st = loop.Run("a", 0, c);
  EXPECT_EQ(st.code(), absl::StatusCode::kCancelled);
  ASSERT_GE(got.size(), 4u);  // snapshot, QUEUED, 2 heartbeats
  EXPECT_TRUE(got.back().has_heartbeat());
  EXPECT_EQ(got.back().sequence(), 1);
}

TEST_F(WatchLoopTest, DrainingEndsWithUnavailableNamingWhereToResume) {
  std::vector<v1::JobEvent> got;
  WatchControls c = Collect(&got);
  std::atomic<bool> draining{false};
  c.draining = [&] { return draining.load(); };
  WatchLoop loop(store_.get(), &bus_, WatchOptions{.heartbeat = 10s, .wait = 10ms});
  std::thread t([&] {
    std::this_thread::sleep_for(50ms);
    draining = true;
  });
  const absl::Status st = loop.Run("a", 0, c);
  t.join();
  EXPECT_EQ(st.code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(std::string(st.message()), HasSubstr("after_sequence=1"));
}

TEST_F(WatchLoopTest, WhileDrainingAWatchOfARunningJobGoesOnUntilTheJobIsRequeued) {
  auto claim = store_->ClaimNext("w", 60000);
  ASSERT_TRUE(claim.ok() && claim->has_value());
  std::vector<v1::JobEvent> got;
  WatchControls c = Collect(&got);
  c.draining = [] { return true; };  // draining from the start: the job runs, so the watch stays
  WatchLoop loop(store_.get(), &bus_, WatchOptions{.heartbeat = 10s, .wait = 10ms});
  std::thread t([&] {
    std::this_thread::sleep_for(50ms);
    v1::Progress p;
    p.set_stage("simplify");
    p.set_message("server draining: 2 s left to finish");
    (*p.mutable_metrics())["drain_remaining_s"] = 2;
    ASSERT_TRUE(store_->AppendProgress((*claim)->lease, p).ok());
    std::this_thread::sleep_for(50ms);
    ASSERT_TRUE(store_->Requeue((*claim)->lease, "requeued").ok());
  });
  const absl::Status st = loop.Run("a", 0, c);
  t.join();
  EXPECT_EQ(st.code(), absl::StatusCode::kUnavailable) << st;
  bool drain = false, queued = false;
  for (const auto& ev : got) {
    drain = drain || (ev.has_progress() && ev.progress().metrics().count("drain_remaining_s"));
    queued = queued || (ev.has_state_change() && ev.state_change().state() == v1::QUEUED &&
                        ev.sequence() > 2);
  }
  EXPECT_TRUE(drain) << "the drain's progress reached the watcher";
  EXPECT_TRUE(queued) << "the requeue reached the watcher";
}

TEST_F(WatchLoopTest, WhenTheBusClosesTheStoreIsReadOnceMoreBeforeTheWatchEnds) {
  auto claim = store_->ClaimNext("w", 60000);
  ASSERT_TRUE(claim.ok() && claim->has_value());
  std::vector<v1::JobEvent> got;
  WatchControls c = Collect(&got);
  c.draining = [] { return true; };
  WatchLoop loop(store_.get(), &bus_, WatchOptions{.heartbeat = 10s, .wait = 10ms});
  std::thread t([&] {
    std::this_thread::sleep_for(50ms);
    // Committed to the store, never published (the store's listener is not told): the watch
    // finds it in the store after the bus closes.
    store_->SetListener(nullptr);
    ASSERT_TRUE(store_->Requeue((*claim)->lease, "requeued").ok());
    bus_.Close();
  });
  const absl::Status st = loop.Run("a", 0, c);
  t.join();
  EXPECT_EQ(st.code(), absl::StatusCode::kUnavailable) << st;
  ASSERT_FALSE(got.empty());
  EXPECT_TRUE(got.back().has_state_change()) << got.back().DebugString();
  EXPECT_EQ(got.back().state_change().state(), v1::QUEUED);
}

TEST_F(WatchLoopTest, AWatcherThatStopsReadingEndsTheLoopAndAnUnknownJobIsNotFound) {
  WatchControls c;
  c.send = [](const v1::JobEvent&) { return false; };
  WatchLoop loop(store_.get(), &bus_);
  EXPECT_EQ(loop.Run("a", 0, c).code(), absl::StatusCode::kCancelled);
  std::vector<v1::JobEvent> got;
  EXPECT_EQ(loop.Run("zzz", 0, Collect(&got)).code(), absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace decima::server
