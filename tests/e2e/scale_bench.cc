// decima-scale-bench: the scale-out figures of issue 12, printed as one JSON object. A real
// PostgreSQL 15 (durable: fsync on) is started in a temp folder; replicas are real
// decima-server processes on loopback sharing one data dir.
//   failover_s:        SIGKILL of the replica running a job -> the job RUNNING on another
//                      replica (client-observed, polled every 10 ms), per run; bound lease*1.25
//   claims_per_s:      claim + finish cycles through the store of 3 replicas (3 PostgresJobStore
//                      instances, 2 threads each, as 3 replicas x 2 workers), no child process:
//                      what the store can hand out
//   watch_delivery_ms: event commit (the event's time, set by the writing replica just before
//                      its commit) -> a watcher on another replica receives it (p50, p99, max)
//   connections_per_replica: the most PostgreSQL connections any replica held during the watch
//                      run (pg_stat_activity by application_name)
//   ct_head:           the whole CT-head job (create -> end, server clock) on one SQLite server
//                      and through a replica of 3 on PostgreSQL, median of --repeat
// Usage: decima-scale-bench [--volume FILE] [--repeat N] [--claims N] [--failovers N]
//                           [--lease-seconds S]
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <signal.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "decima/v1/jobs.grpc.pb.h"
#include "server/store/job_store.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/postgres_server.h"
#include "tests/testing/test_data.h"

namespace fs = std::filesystem;
using namespace decima;
using namespace std::chrono_literals;
using google::protobuf::util::TimeUtil;

namespace {

double Percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[static_cast<size_t>(p * (v.size() - 1) + 0.5)];
}

double NowSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

double Seconds(const google::protobuf::Timestamp& t) { return t.seconds() + t.nanos() * 1e-9; }

std::unique_ptr<v1::Jobs::Stub> Stub(const std::string& address) {
  return v1::Jobs::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
}

std::optional<v1::Job> GetJob(const std::string& address, const std::string& name) {
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + 10s);
  v1::GetJobRequest req;
  req.set_name(name);
  v1::Job job;
  if (!Stub(address)->GetJob(&ctx, req, &job).ok()) return std::nullopt;
  return job;
}

bool Final(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

struct Cluster {
  decima::testing::PostgresServer* pg;
  std::string db;
  fs::path data;
  double lease_seconds;
  std::vector<std::unique_ptr<e2e::ServerProcess>> replicas;

  void Add(int workers) {
    replicas.push_back(std::make_unique<e2e::ServerProcess>(
        data, std::vector<std::string>{"--store", pg->Dsn(db), "--workers", std::to_string(workers),
                                       "--lease-seconds", std::to_string(lease_seconds),
                                       "--allow-faults", "--drain-seconds", "1"}));
  }
  std::string Submit(size_t i, const fs::path& volume, const std::string& fault,
                     int image_size = 64) {
    std::vector<std::string> args = {"submit", volume.string(), "--image-size",
                                     std::to_string(image_size)};
    if (!fault.empty()) {
      args.push_back("--fault");
      args.push_back(fault);
    }
    e2e::CliResult r = e2e::RunCli(replicas[i]->address(), args);
    if (r.rc != 0) std::fprintf(stderr, "submit: %s\n", r.err.c_str());
    return e2e::FirstLine(r.out);
  }
  int RunnerOf(const std::string& job, int attempt) {
    const std::string needle =
        "job " + job.substr(5) + " RUNNING attempt " + std::to_string(attempt) + " ";
    int found = -1;
    e2e::WaitFor(
        [&] {
          for (size_t i = 0; i < replicas.size(); ++i) {
            if (replicas[i]->pid() > 0 && replicas[i]->Log().find(needle) != std::string::npos) {
              found = static_cast<int>(i);
              return true;
            }
          }
          return false;
        },
        30s);
    return found;
  }
};

std::string NewDatabase(decima::testing::PostgresServer& pg) {
  static int n = 0;
  std::string db = "bench" + std::to_string(n++);
  std::string err = pg.CreateDatabase(db);
  if (!err.empty()) std::fprintf(stderr, "%s\n", err.c_str());
  return db;
}

nlohmann::json Failover(decima::testing::PostgresServer& pg, const fs::path& scratch,
                        const fs::path& volume, int runs, double lease) {
  std::vector<double> secs;
  for (int run = 0; run < runs; ++run) {
    Cluster c{&pg, NewDatabase(pg), scratch / ("failover" + std::to_string(run)), lease, {}};
    for (int i = 0; i < 3; ++i) c.Add(1);
    const std::string job = c.Submit(0, volume, "sleep:120");
    const int runner = c.RunnerOf(job, 1);
    if (runner < 0) continue;
    // Kill at a random point of the renew cycle, as a real crash would.
    std::this_thread::sleep_for(std::chrono::milliseconds(200 + 397 * run % 1000));
    const auto t0 = std::chrono::steady_clock::now();
    c.replicas[runner]->Kill(SIGKILL);
    const std::string other = c.replicas[(runner + 1) % 3]->address();
    bool moved = e2e::WaitFor(
        [&] {
          auto j = GetJob(other, job);
          return j && j->state() == v1::RUNNING && j->attempts() == 2;
        },
        std::chrono::milliseconds(static_cast<int64_t>(lease * 4000)));
    if (moved)
      secs.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
  double worst = secs.empty() ? 0 : *std::max_element(secs.begin(), secs.end());
  return {{"runs", secs},
          {"max", worst},
          {"lease_s", lease},
          {"bound_s", lease * 1.25},
          {"within_bound", !secs.empty() && worst <= lease * 1.25}};
}

nlohmann::json Claims(decima::testing::PostgresServer& pg, int jobs) {
  const std::string dsn = pg.Dsn(NewDatabase(pg));
  std::vector<std::unique_ptr<server::JobStore>> stores;
  for (int i = 0; i < 3; ++i) {
    server::PostgresStoreOptions o;
    o.connections = 8;
    auto s = server::OpenPostgresJobStore(dsn, o);
    if (!s.ok()) return {{"error", s.status().ToString()}};
    stores.push_back(std::move(*s));
  }
  v1::JobSpec spec;
  spec.set_volume("volumes/bench");
  for (int i = 0; i < jobs; ++i) {
    bool created = false;
    (void)stores[i % 3]->CreateJob("c" + std::to_string(i), spec, "", 0, "", &created);
  }
  std::atomic<int> claimed{0}, errors{0};
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<std::thread> threads;
  for (int t = 0; t < 6; ++t) {
    threads.emplace_back([&, t] {
      server::JobStore* s = stores[t % 3].get();
      for (int guard = 0; guard < jobs; ++guard) {
        auto c = s->ClaimNext("bench" + std::to_string(t), 60000);
        if (!c.ok()) {
          ++errors;
          return;
        }
        if (!c->has_value()) return;
        if (!s->Finish((*c)->lease, v1::SUCCEEDED, v1::Job()).ok()) ++errors;
        ++claimed;
      }
    });
  }
  for (auto& t : threads) t.join();
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return {{"claims", claimed.load()},
          {"errors", errors.load()},
          {"seconds", secs},
          {"claims_per_s", claimed.load() / secs},
          {"replicas", 3},
          {"threads_per_replica", 2}};
}

// Watchers on replicas that do not run the job; the delay from each event's time to its
// arrival. Also samples the connections each replica holds meanwhile.
nlohmann::json WatchDelivery(decima::testing::PostgresServer& pg, const fs::path& scratch,
                             const fs::path& volume, nlohmann::json* connections) {
  Cluster c{&pg, NewDatabase(pg), scratch / "watch", 15, {}};
  for (int i = 0; i < 3; ++i) c.Add(2);
  std::vector<std::string> jobs;
  for (int i = 0; i < 6; ++i) jobs.push_back(c.Submit(i % 3, volume, "sleep:6"));
  std::mutex mu;
  std::vector<double> delays;
  std::atomic<bool> done{false};
  std::vector<std::thread> watchers;
  for (const auto& job : jobs) {
    const int runner = c.RunnerOf(job, 1);
    for (int k = 1; k <= 2; ++k) {
      const std::string addr = c.replicas[(runner + k) % 3]->address();
      watchers.emplace_back([&, addr, job] {
        grpc::ClientContext ctx;
        ctx.set_deadline(std::chrono::system_clock::now() + 120s);
        v1::WatchJobRequest req;
        req.set_name(job);
        v1::JobEvent ev;
        auto reader = Stub(addr)->WatchJob(&ctx, req);
        int64_t after = 0;
        bool live = false;
        while (reader->Read(&ev)) {
          const double now = NowSeconds();
          if (ev.has_snapshot()) {
            after = ev.sequence();  // events up to here were read from the store, not live
            live = true;
            continue;
          }
          if (!live || ev.has_heartbeat() || ev.sequence() <= after) continue;
          std::lock_guard<std::mutex> lock(mu);
          delays.push_back((now - Seconds(ev.time())) * 1000);
        }
        reader->Finish();
      });
    }
  }
  std::map<std::string, int> most;
  std::thread sampler([&] {
    while (!done) {
      auto out = pg.Sql(
          "SELECT split_part(application_name, ' ', 2), COUNT(*) FROM pg_stat_activity "
          "WHERE application_name LIKE 'decima-server %' GROUP BY 1",
          c.db);
      if (out) {
        std::stringstream ss(*out);
        std::string line;
        while (std::getline(ss, line)) {
          auto bar = line.find('|');
          if (bar == std::string::npos) continue;
          int n = std::atoi(line.c_str() + bar + 1);
          auto& m = most[line.substr(0, bar)];
          m = std::max(m, n);
        }
      }
      std::this_thread::sleep_for(200ms);
    }
  });
  for (auto& w : watchers) w.join();
  done = true;
  sampler.join();
  int worst = 0;
  for (const auto& [owner, n] : most) worst = std::max(worst, n);
  *connections = {{"max", worst}, {"replicas_seen", most.size()}};
  return {{"events", delays.size()},
          {"p50", Percentile(delays, 0.5)},
          {"p99", Percentile(delays, 0.99)},
          {"max", delays.empty() ? 0 : *std::max_element(delays.begin(), delays.end())}};
}

double JobSeconds(const std::string& address, const std::string& job) {
  e2e::WaitFor(
      [&] {
        auto j = GetJob(address, job);
        return j && Final(j->state());
      },
      600s);
  auto j = GetJob(address, job);
  if (!j || j->state() != v1::SUCCEEDED) return -1;
  return Seconds(j->end_time()) - Seconds(j->create_time());
}

nlohmann::json CtHead(decima::testing::PostgresServer& pg, const fs::path& scratch, const fs::path& ct,
                      int repeat) {
  std::vector<double> sqlite, postgres;
  // Both set-ups are up at once and their jobs alternate, one at a time, so a change of the
  // machine's load affects both alike.
  e2e::ServerProcess server(scratch / "sqlite", {"--workers", "1"});
  Cluster c{&pg, NewDatabase(pg), scratch / "pg-ct", 15, {}};
  for (int i = 0; i < 3; ++i) c.Add(1);
  for (int i = 0; i < repeat; ++i) {
    e2e::CliResult r = e2e::RunCli(server.address(), {"submit", ct.string()}, 600s);
    sqlite.push_back(JobSeconds(server.address(), e2e::FirstLine(r.out)));
    // Submitted through one replica, read through another; any may run it.
    r = e2e::RunCli(c.replicas[i % 3]->address(), {"submit", ct.string()}, 600s);
    postgres.push_back(JobSeconds(c.replicas[(i + 1) % 3]->address(), e2e::FirstLine(r.out)));
  }
  const double a = Percentile(sqlite, 0.5), b = Percentile(postgres, 0.5);
  return {{"volume", ct.filename().string()}, {"sqlite_single_server_s", sqlite},
          {"postgres_replica_s", postgres},   {"median_sqlite_s", a},
          {"median_postgres_s", b},           {"postgres_over_sqlite", a > 0 ? b / a - 1 : 0}};
}

}  // namespace

int main(int argc, char** argv) {
  fs::path ct;
  int repeat = 3, claims = 3000, failovers = 3;
  double lease = 4;
  for (int i = 1; i + 1 < argc; i += 2) {
    std::string k = argv[i];
    if (k == "--volume") ct = argv[i + 1];
    if (k == "--repeat") repeat = std::atoi(argv[i + 1]);
    if (k == "--claims") claims = std::atoi(argv[i + 1]);
    if (k == "--failovers") failovers = std::atoi(argv[i + 1]);
    if (k == "--lease-seconds") lease = std::atof(argv[i + 1]);
  }
  if (ct.empty()) {
    if (auto f = decima::testing::SharedDataFile("ct-head-128x128x53.nii.gz")) ct = *f;
  }
  if (!decima::testing::PostgresServer::BinDir()) {
    std::fprintf(stderr, "%s\n", decima::testing::PostgresServer::WhyAbsent().c_str());
    return 1;
  }
  decima::testing::PostgresServer pg(/*durable=*/true);
  if (!pg.error().empty()) {
    std::fprintf(stderr, "%s\n", pg.error().c_str());
    return 1;
  }
  const fs::path scratch = decima::testing::MakeScratchDir("scale_bench");
  const fs::path tiny = scratch / "tiny.nii";
  e2e::WriteTinyNifti(tiny, 12, 10, 8);
  nlohmann::json out;
  out["claims"] = Claims(pg, claims);
  out["failover_s"] = Failover(pg, scratch, tiny, failovers, lease);
  nlohmann::json connections;
  out["watch_delivery_ms"] = WatchDelivery(pg, scratch, tiny, &connections);
  out["connections_per_replica"] = connections;
  if (!ct.empty()) {
    out["ct_head"] = CtHead(pg, scratch, ct, repeat);
  } else {
    out["ct_head"] = "skipped: no --volume and no ct-head-128x128x53.nii.gz in the shared data";
  }
  std::printf("%s\n", out.dump(2).c_str());
  return 0;
}
