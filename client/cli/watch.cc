#include "client/cli/watch.h"

#include <mutex>
#include <thread>

#include "client/cli/describe.h"
#include "client/cli/interrupt.h"
#include "client/cli/job_event_stream.h"
#include "client/cli/progress_view.h"

namespace decima::client {

namespace {

// The job's stream on the context's channel, retried for --reconnect.
JobEventStream StreamOf(CliContext& ctx, v1::Jobs::StubInterface* stub, const std::string& name) {
  ReconnectPolicy p;
  p.give_up_after = std::chrono::milliseconds(static_cast<int64_t>(ctx.flags.reconnect_s * 1000));
  return JobEventStream(
      stub, [&ctx] { return ctx.conn.Context(false); }, name, p, &ctx.ever_connected);
}

}  // namespace

int Watch(CliContext& ctx, const std::string& name, v1::Job* final) {
  auto stub = v1::Jobs::NewStub(ctx.conn.channel);
  ArmInterrupt(ctx, name);
  ProgressView view(name, stderr, ctx.stderr_tty, ctx.Quiet(), TerminalColumns);
  JobEventStream stream = StreamOf(ctx, stub.get(), name);
  JobEventStream::Handlers h;
  h.event = [&](const v1::JobEvent& ev) {
    if (ctx.JsonOut()) {
      std::printf("%s\n", ToJson(ev).c_str());
      std::fflush(stdout);
    }
    if (ev.has_snapshot()) *final = ev.snapshot();
    view.OnEvent(ev, stream.last_sequence() == 0);
  };
  h.stream_ended = [&] { view.EndStream(); };
  h.reconnected = [&](int attempts) {
    view.Say("decima: reconnected to " + ctx.flags.server + " after " + std::to_string(attempts) +
             " attempt(s)");
  };
  h.outage = [&](const grpc::Status& s) {
    const std::string why = s.error_code() == grpc::StatusCode::CANCELLED
                                ? "the server closed the stream"
                                : s.error_message();
    view.Say("decima: watch " + name + ": server unavailable (" + why +
             "); reconnecting for up to " + FormatDuration(ctx.flags.reconnect_s));
  };
  h.gave_up = [&](int attempts) {
    view.Say("decima: watch " + name + ": gave up after " + std::to_string(attempts) +
             " reconnection attempts");
  };
  const grpc::Status s = stream.Follow(h);
  if (!s.ok()) return Report(ctx, s, "watch " + name);
  // The stream ends after the final state (or at once for a job already final).
  v1::GetJobRequest greq;
  greq.set_name(name);
  grpc::Status gs =
      WithRetry(ctx, [&] { return stub->GetJob(ctx.conn.Context().get(), greq, final); });
  if (!gs.ok()) return Report(ctx, gs, "get " + name);
  DisarmInterrupt();
  // -q hides progress, never why a job did not succeed.
  if (ctx.flags.quiet && !ctx.JsonOut() && final->state() != v1::SUCCEEDED) {
    std::fprintf(stderr, "decima: %s %s%s%s\n", name.c_str(),
                 v1::JobState_Name(final->state()).c_str(),
                 final->error().message().empty() ? "" : ": ",
                 TerminalSafe(final->error().message()).c_str());
  }
  if (final->state() == v1::SUCCEEDED) return PrintSummary(ctx, *final);
  return ExitCodeFor(final->state());
}

std::vector<WatchOutcome> WatchMany(CliContext& ctx, const std::vector<std::string>& names) {
  std::mutex mu;  // one whole line at a time on stdout and stderr
  auto say = [&](const std::string& text) {
    if (ctx.Quiet()) return;
    std::lock_guard<std::mutex> lock(mu);
    std::fprintf(stderr, "%s\n", text.c_str());
  };
  std::vector<WatchOutcome> out(names.size());
  auto follow = [&](size_t i) {
    const std::string& name = names[i];
    const std::string id = ShortId(name);
    auto stub = v1::Jobs::NewStub(ctx.conn.channel);
    JobLinesView view(id, say);
    JobEventStream stream = StreamOf(ctx, stub.get(), name);
    JobEventStream::Handlers h;
    h.event = [&](const v1::JobEvent& ev) {
      if (ctx.JsonOut()) {
        std::lock_guard<std::mutex> lock(mu);
        std::printf("%s\n", ToJson(ev).c_str());
        std::fflush(stdout);
      }
      view.OnEvent(ev, stream.last_sequence() == 0);
    };
    h.reconnected = [&](int attempts) {
      say(id + " reconnected after " + std::to_string(attempts) + " attempt(s)");
    };
    h.outage = [&](const grpc::Status& s) {
      say(id + " server unavailable (" + s.error_message() + "); reconnecting for up to " +
          FormatDuration(ctx.flags.reconnect_s));
    };
    const grpc::Status s = stream.Follow(h);
    if (!s.ok()) {
      out[i].rc = ExitCodeFor(s.error_code());
      out[i].error = StatusCodeName(s.error_code()) + ": " + s.error_message();
      std::lock_guard<std::mutex> lock(mu);
      std::fprintf(stderr, "decima: watch %s: %s\n", name.c_str(), out[i].error.c_str());
      return;
    }
    // The stream ends after the final state (at once for a job already final).
    v1::GetJobRequest greq;
    greq.set_name(name);
    const grpc::Status gs =
        WithRetry(ctx, [&] { return stub->GetJob(ctx.conn.Context().get(), greq, &out[i].final); });
    if (!gs.ok()) {
      out[i].rc = ExitCodeFor(gs.error_code());
      out[i].error = StatusCodeName(gs.error_code()) + ": " + gs.error_message();
      return;
    }
    const v1::Job& f = out[i].final;
    out[i].rc = f.state() == v1::SUCCEEDED ? (SummarizeJob(f, 0).Met() ? kOk : kTargetNotReached)
                                           : ExitCodeFor(f.state());
  };
  ArmInterruptMany(ctx, names);
  std::vector<std::thread> threads;
  threads.reserve(names.size());
  for (size_t i = 0; i < names.size(); ++i) threads.emplace_back(follow, i);
  for (auto& t : threads) t.join();
  DisarmInterrupt();
  return out;
}

void SetOutcome(const WatchOutcome& o, StudyRow* row) {
  row->rc = o.rc;
  if (!o.error.empty()) {
    row->state = "UNKNOWN";
    row->detail = "watch: " + o.error;
    return;
  }
  row->state = v1::JobState_Name(o.final.state());
  if (o.final.state() == v1::SUCCEEDED) {
    const JobSummary s = SummarizeJob(o.final, 0);
    row->detail = "reduction " + Percent(s.achieved_reduction, 1) + " (target " +
                  Percent(s.target_reduction, 1) + ")" +
                  (s.reached_target ? "" : ", short: " + s.stop_message);
  } else {
    row->detail = o.final.error().message();
  }
}

}  // namespace decima::client
