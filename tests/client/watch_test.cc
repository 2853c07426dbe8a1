// The two halves of `decima watch` on their own: JobEventStream against a real in-process gRPC
// server whose WatchJob drops the stream every few events (no gap, no duplicate, resumed from
// the sequence asked, backoff doubling to its bound, giving up), and the progress views fed
// events directly (what lines a job's progress makes).
#include <grpcpp/grpcpp.h>
#include <stdio.h>

#include <atomic>
#include <mutex>
#include <string>
#include <vector>

#include "client/cli/job_event_stream.h"
#include "client/cli/progress_view.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace decima::client {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using namespace std::chrono_literals;

// A job of `total` progress events then SUCCEEDED (sequence total + 1). Each WatchJob sends
// the snapshot, then the events after the sequence asked; it ends the stream with UNAVAILABLE
// after `per_stream` of them (a server going away), and refuses the first `refusals` calls after
// each drop outright (the server still down).
class ScriptedJobs final : public v1::Jobs::Service {
 public:
  ScriptedJobs(int total, int per_stream, int refusals)
      : total_(total), per_stream_(per_stream), refusals_(refusals) {}

  grpc::Status WatchJob(grpc::ServerContext*, const v1::WatchJobRequest* req,
                        grpc::ServerWriter<v1::JobEvent>* writer) override {
    {
      std::lock_guard<std::mutex> lock(mu_);
      asked_.push_back(req->after_sequence());
      if (refuse_left_ > 0) {
        --refuse_left_;
        return grpc::Status(grpc::StatusCode::UNAVAILABLE, "still down");
      }
    }
    v1::JobEvent snapshot;
    snapshot.set_sequence(req->after_sequence());
    snapshot.mutable_snapshot()->set_name(req->name());
    snapshot.mutable_snapshot()->set_state(v1::RUNNING);
    snapshot.mutable_snapshot()->set_last_sequence(req->after_sequence());
    writer->Write(snapshot);
    int sent = 0;
    for (int64_t seq = req->after_sequence() + 1; seq <= total_ + 1; ++seq) {
      if (per_stream_ > 0 && sent == per_stream_) {
        std::lock_guard<std::mutex> lock(mu_);
        refuse_left_ = refusals_;
        return grpc::Status(grpc::StatusCode::UNAVAILABLE, "server restarting");
      }
      v1::JobEvent ev;
      ev.set_sequence(seq);
      if (seq <= total_) {
        ev.mutable_progress()->set_stage("simplify");
        ev.mutable_progress()->set_fraction(static_cast<double>(seq) / total_);
      } else {
        ev.mutable_state_change()->set_state(v1::SUCCEEDED);
      }
      writer->Write(ev);
      ++sent;
      // A heartbeat between events: it carries no new sequence.
      v1::JobEvent hb;
      hb.set_sequence(seq);
      hb.mutable_heartbeat();
      writer->Write(hb);
    }
    return grpc::Status::OK;
  }

  std::vector<int64_t> asked() {
    std::lock_guard<std::mutex> lock(mu_);
    return asked_;
  }

 private:
  const int total_, per_stream_, refusals_;
  std::mutex mu_;
  int refuse_left_ = 0;
  std::vector<int64_t> asked_;
};

struct InProcessServer {
  explicit InProcessServer(grpc::Service* service) {
    grpc::ServerBuilder b;
    b.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    b.RegisterService(service);
    server = b.BuildAndStart();
    channel = grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                  grpc::InsecureChannelCredentials());
    stub = v1::Jobs::NewStub(channel);
  }
  ~InProcessServer() { server->Shutdown(); }
  int port = 0;
  std::unique_ptr<grpc::Server> server;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::Jobs::Stub> stub;
};

std::unique_ptr<grpc::ClientContext> NewContext() {
  return std::make_unique<grpc::ClientContext>();
}

TEST(CliJobEventStream, DropsEveryThreeEventsResumeWithNoGapAndNoDuplicate) {
  ScriptedJobs jobs(/*total=*/20, /*per_stream=*/3, /*refusals=*/0);
  InProcessServer s(&jobs);
  std::atomic<bool> ever_connected{false};
  JobEventStream stream(s.stub.get(), NewContext, "jobs/j", ReconnectPolicy{}, &ever_connected);
  std::vector<std::chrono::milliseconds> waits;
  stream.sleep = [&](std::chrono::milliseconds d) { waits.push_back(d); };
  std::vector<int64_t> seen;
  int outages = 0, reconnects = 0, snapshots = 0;
  JobEventStream::Handlers h;
  h.event = [&](const v1::JobEvent& ev) {
    if (ev.has_snapshot()) {
      ++snapshots;
    } else if (!ev.has_heartbeat()) {
      seen.push_back(ev.sequence());
    }
  };
  h.outage = [&](const grpc::Status& st) {
    ++outages;
    EXPECT_EQ(st.error_code(), grpc::StatusCode::UNAVAILABLE);
  };
  h.reconnected = [&](int attempts) {
    ++reconnects;
    EXPECT_EQ(attempts, 1);
  };
  const grpc::Status st = stream.Follow(h);
  ASSERT_TRUE(st.ok()) << st.error_message();
  std::vector<int64_t> expected;
  for (int64_t i = 1; i <= 21; ++i) expected.push_back(i);
  EXPECT_EQ(seen, expected);  // every event once, in order: no gap, no duplicate
  EXPECT_EQ(stream.last_sequence(), 21);
  // Each stream asked from the last sequence the one before delivered.
  EXPECT_THAT(jobs.asked(), ElementsAre(0, 3, 6, 9, 12, 15, 18));
  EXPECT_EQ(outages, 6);
  EXPECT_EQ(reconnects, 6);
  EXPECT_EQ(snapshots, 7);
  // An event resets the backoff: each outage waited the first step only.
  EXPECT_EQ(waits, std::vector<std::chrono::milliseconds>(6, 100ms));
  EXPECT_TRUE(ever_connected);
}

TEST(CliJobEventStream, BackoffDoublesUpToItsBoundAndOneNoticePerOutage) {
  ScriptedJobs jobs(/*total=*/4, /*per_stream=*/2, /*refusals=*/6);
  InProcessServer s(&jobs);
  std::atomic<bool> ever_connected{false};
  JobEventStream stream(s.stub.get(), NewContext, "jobs/j", ReconnectPolicy{}, &ever_connected);
  std::vector<std::chrono::milliseconds> waits;
  stream.sleep = [&](std::chrono::milliseconds d) { waits.push_back(d); };
  std::vector<int64_t> seen;
  int outages = 0;
  std::vector<int> reconnected_after;
  JobEventStream::Handlers h;
  h.event = [&](const v1::JobEvent& ev) {
    if (!ev.has_snapshot() && !ev.has_heartbeat()) seen.push_back(ev.sequence());
  };
  h.outage = [&](const grpc::Status&) { ++outages; };
  h.reconnected = [&](int attempts) { reconnected_after.push_back(attempts); };
  ASSERT_TRUE(stream.Follow(h).ok());
  EXPECT_THAT(seen, ElementsAre(1, 2, 3, 4, 5));
  // Two drops, each followed by 6 refused calls: 7 failed attempts per outage.
  EXPECT_EQ(outages, 2);
  EXPECT_THAT(reconnected_after, ElementsAre(7, 7));
  const std::vector<std::chrono::milliseconds> one_outage = {100ms,  200ms,  400ms, 800ms,
                                                             1000ms, 1000ms, 1000ms};
  std::vector<std::chrono::milliseconds> both = one_outage;
  both.insert(both.end(), one_outage.begin(), one_outage.end());
  EXPECT_EQ(waits, both);
}

TEST(CliJobEventStream, GivesUpAfterThePolicyAndNeverRetriesBeforeFirstContact) {
  // Every call refused: the server never answered, so the first failure is final.
  ScriptedJobs jobs(/*total=*/4, /*per_stream=*/0, /*refusals=*/0);
  {
    std::atomic<bool> ever_connected{false};
    InProcessServer down(&jobs);
    down.server->Shutdown();
    JobEventStream stream(down.stub.get(), NewContext, "jobs/j", ReconnectPolicy{},
                          &ever_connected);
    int sleeps = 0;
    stream.sleep = [&](std::chrono::milliseconds) { ++sleeps; };
    const grpc::Status st = stream.Follow({});
    EXPECT_EQ(st.error_code(), grpc::StatusCode::UNAVAILABLE);
    EXPECT_EQ(sleeps, 0);
  }
  // A server that answered once and then stays away: retried until give_up_after has passed
  // since the last event, then the stream's status, with the number of attempts.
  ScriptedJobs flaky(/*total=*/100, /*per_stream=*/1, /*refusals=*/1000000);
  InProcessServer t(&flaky);
  std::atomic<bool> ever_connected{false};
  ReconnectPolicy policy;
  policy.give_up_after = 300ms;
  JobEventStream stream(t.stub.get(), NewContext, "jobs/j", policy, &ever_connected);
  int gave_up = 0;
  JobEventStream::Handlers h;
  h.gave_up = [&](int attempts) { gave_up = attempts; };
  const auto t0 = std::chrono::steady_clock::now();
  const grpc::Status st = stream.Follow(h);
  const auto took = std::chrono::steady_clock::now() - t0;
  EXPECT_EQ(st.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ(stream.last_sequence(), 1);
  // 100 + 200 ms of waits fit in 300 ms; the third attempt comes after the deadline.
  EXPECT_GE(gave_up, 2);
  EXPECT_LE(gave_up, 4);
  EXPECT_GE(took, 300ms);
  EXPECT_LT(took, 300ms + 1000ms + 2s);  // the deadline plus at most one bounded wait
}

// What a ProgressView printed to a memory stream.
struct Captured {
  Captured() { file = open_memstream(&buf, &size); }
  ~Captured() {
    std::fclose(file);
    std::free(buf);
  }
  std::string text() {
    std::fflush(file);
    return std::string(buf, size);
  }
  std::FILE* file = nullptr;
  char* buf = nullptr;
  size_t size = 0;
};

v1::JobEvent Snapshot(v1::JobState state, int64_t last_sequence) {
  v1::JobEvent ev;
  ev.set_sequence(last_sequence);
  ev.mutable_snapshot()->set_name("jobs/abc");
  ev.mutable_snapshot()->set_state(state);
  ev.mutable_snapshot()->set_last_sequence(last_sequence);
  return ev;
}

v1::JobEvent Progress(int64_t seq, const std::string& stage, double fraction) {
  v1::JobEvent ev;
  ev.set_sequence(seq);
  ev.mutable_time()->set_seconds(1000 + seq);
  ev.mutable_progress()->set_stage(stage);
  ev.mutable_progress()->set_fraction(fraction);
  ev.mutable_progress()->set_message("msg " + std::to_string(seq));
  return ev;
}

v1::JobEvent State(int64_t seq, v1::JobState state, const std::string& error = "") {
  v1::JobEvent ev;
  ev.set_sequence(seq);
  ev.mutable_time()->set_seconds(1000 + seq);
  ev.mutable_state_change()->set_state(state);
  ev.mutable_state_change()->mutable_error()->set_message(error);
  return ev;
}

std::vector<std::string> Lines(const std::string& s) {
  std::vector<std::string> out;
  size_t at = 0;
  for (size_t nl; (nl = s.find('\n', at)) != std::string::npos; at = nl + 1) {
    out.push_back(s.substr(at, nl - at));
  }
  return out;
}

TEST(CliProgressView, PlainLinesOnePerStageAndStateWithTheFirstContactFirst) {
  Captured out;
  ProgressView view("jobs/abc", out.file, /*tty=*/false, /*quiet=*/false, [] { return 80; });
  view.OnEvent(Snapshot(v1::QUEUED, 0), /*first_contact=*/true);
  view.OnEvent(State(1, v1::RUNNING), false);
  view.OnEvent(Progress(2, "segment", 0.5), false);
  view.OnEvent(Progress(3, "segment", 0.51), false);  // same stage, same tenth: no line
  view.OnEvent(Progress(4, "simplify", 0.5), false);
  view.OnEvent(State(5, v1::FAILED, "simplify: out of memory"), false);
  const auto lines = Lines(out.text());
  ASSERT_EQ(lines.size(), 5u) << out.text();
  EXPECT_EQ(lines[0], "decima: watching jobs/abc: QUEUED");
  EXPECT_EQ(lines[1], "abc RUNNING");
  EXPECT_THAT(lines[2], HasSubstr("segment"));
  EXPECT_THAT(lines[2], HasSubstr("msg 2"));
  EXPECT_THAT(lines[3], HasSubstr("simplify"));
  EXPECT_EQ(lines[4], "abc FAILED after 0:04: simplify: out of memory");
}

TEST(CliProgressView, ReplayedEventsOnlyBringTheBarUpToDateAndQuietPrintsNothing) {
  Captured out;
  ProgressView view("jobs/abc", out.file, /*tty=*/false, /*quiet=*/false, [] { return 80; });
  view.OnEvent(Snapshot(v1::RUNNING, 3), /*first_contact=*/true);
  view.OnEvent(State(1, v1::RUNNING), false);
  view.OnEvent(Progress(2, "segment", 0.5), false);
  view.OnEvent(Progress(3, "tetra", 1.0), false);  // the last replayed: one bar line
  const auto lines = Lines(out.text());
  ASSERT_EQ(lines.size(), 2u) << out.text();
  EXPECT_THAT(lines[0], HasSubstr("decima: watching jobs/abc: RUNNING"));
  EXPECT_THAT(lines[1], HasSubstr("tetra"));

  Captured quiet;
  ProgressView hushed("jobs/abc", quiet.file, false, /*quiet=*/true, [] { return 80; });
  hushed.OnEvent(Snapshot(v1::QUEUED, 0), true);
  hushed.OnEvent(Progress(1, "segment", 0.5), false);
  hushed.Say("anything");
  EXPECT_EQ(quiet.text(), "");
}

TEST(CliProgressView, ATerminalBarIsRedrawnInPlaceAndEndsItsLine) {
  Captured out;
  ProgressView view("jobs/abc", out.file, /*tty=*/true, /*quiet=*/false, [] { return 60; });
  view.OnEvent(Snapshot(v1::RUNNING, 0), true);
  view.OnEvent(Progress(1, "segment", 0.5), false);
  view.OnEvent(Progress(2, "segment", 0.6), false);
  view.EndStream();
  const std::string text = out.text();
  EXPECT_EQ(std::count(text.begin(), text.end(), '\r'), 2) << text;
  EXPECT_EQ(text.back(), '\n');
  for (const auto& l : Lines(text)) {
    const size_t cr = l.rfind("\033[K");
    EXPECT_LT(cr == std::string::npos ? l.size() : l.size() - cr - 3, 60u) << l;
  }
}

TEST(CliJobLinesView, IdPrefixedLinesPerStagePerTenthAndPerStateChange) {
  std::vector<std::string> said;
  JobLinesView view("abc", [&](const std::string& l) { said.push_back(l); });
  view.OnEvent(Snapshot(v1::RUNNING, 1), true);
  view.OnEvent(Progress(1, "load", 1.0), false);  // replayed: counted, not said
  view.OnEvent(Progress(2, "segment", 0.1), false);
  view.OnEvent(Progress(3, "segment", 0.11), false);
  view.OnEvent(State(4, v1::SUCCEEDED), false);
  ASSERT_EQ(said.size(), 3u);
  EXPECT_EQ(said[0], "abc RUNNING");
  EXPECT_THAT(said[1], ::testing::StartsWith("abc "));
  EXPECT_THAT(said[1], HasSubstr(" segment msg 2"));
  EXPECT_EQ(said[2], "abc SUCCEEDED");
}

}  // namespace
}  // namespace decima::client
