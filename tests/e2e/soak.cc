// decima-soak: N jobs from M client threads against a real decima-server while the server is
// restarted (SIGTERM: graceful drain; SIGKILL: crash) and job processes are killed, interleaved.
// Prints one JSON object:
//   jobs: submitted, succeeded, failed (apart: those whose process the soak killed), cancelled,
//         lost (a request whose job is missing or never ended), duplicated (jobs beyond one per
//         request), attempts histogram; the exit code is 1 if any is lost, duplicated or failed
//         for another reason;
//   chaos: how many of each disruption happened;
//   server: RSS (MB) and open fds sampled every second (curves downsampled to <= 60 points);
//   data_dir: bytes and files when empty (first start, server stopped), at the end of the run,
//             and after every job and volume was deleted (server stopped; should equal the
//             empty size), per top-level entry.
// Usage: decima-soak [--jobs N] [--clients M] [--workers W] [--chaos-seconds S]
//                    [--in-flight K] [--timeout-seconds T] [--keep]
// A client keeps at most K of its jobs unfinished, so submissions go on through the whole run
// and meet the restarts (default 2).
// Each job uploads its own tiny synthetic NIfTI (12x10x8 int16, distinct bytes), creates a
// volume and a job, every call with retries across restarts (request ids make them idempotent).
#include <dirent.h>
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "server/util/sha256.h"
#include "tests/e2e/e2e_util.h"

namespace fs = std::filesystem;
using namespace decima;
using namespace std::chrono_literals;
using nlohmann::json;

namespace {

struct Options {
  int jobs = 1000;
  int clients = 4;
  int workers = 2;
  double chaos_seconds = 8;
  double blob_grace_seconds = 5;  // the server's --blob-grace-seconds (default there: 1 hour)
  int in_flight = 2;  // unfinished jobs per client before it waits: submits spread over the run
  double timeout_seconds = 7200;
  bool keep = false;
};

double Now() {
  static const auto t0 = std::chrono::steady_clock::now();
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The running server; replaced on every restart (a new port each time).
class ServerSlot {
 public:
  ServerSlot(fs::path data_dir, std::vector<std::string> flags)
      : data_dir_(std::move(data_dir)), flags_(std::move(flags)) {
    Start();
  }
  void Start() {
    auto s = std::make_unique<e2e::ServerProcess>(data_dir_, flags_);
    std::lock_guard<std::mutex> l(mu_);
    address_ = s->address();
    pid_ = s->pid();
    server_ = std::move(s);
  }
  // Stops the server with `sig` (reaped), then starts a new one on the same data dir.
  void Restart(int sig) {
    std::unique_ptr<e2e::ServerProcess> old;
    {
      std::lock_guard<std::mutex> l(mu_);
      old = std::move(server_);
      pid_ = -1;
    }
    old->Kill(sig);
    old.reset();
    Start();
  }
  void Stop() {
    std::lock_guard<std::mutex> l(mu_);
    if (server_) server_->Kill(SIGTERM);
    server_.reset();
    pid_ = -1;
  }
  std::string address() const {
    std::lock_guard<std::mutex> l(mu_);
    return address_;
  }
  pid_t pid() const {
    std::lock_guard<std::mutex> l(mu_);
    return pid_;
  }

 private:
  const fs::path data_dir_;
  const std::vector<std::string> flags_;
  mutable std::mutex mu_;
  std::unique_ptr<e2e::ServerProcess> server_;
  std::string address_;
  pid_t pid_ = -1;
};

bool Transient(grpc::StatusCode c) {
  return c == grpc::StatusCode::UNAVAILABLE || c == grpc::StatusCode::DEADLINE_EXCEEDED ||
         c == grpc::StatusCode::CANCELLED || c == grpc::StatusCode::ABORTED ||
         c == grpc::StatusCode::RESOURCE_EXHAUSTED;
}

// Calls `call(channel, ctx)` until it answers a non-transient status (at most ~10 minutes of
// retries: a restart takes seconds); returns the last status.
template <typename Call>
grpc::Status Retry(ServerSlot& server, Call call, std::atomic<int64_t>* retries) {
  grpc::Status s;
  for (int attempt = 0; attempt < 3000; ++attempt) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + 20s);
    // A channel per address: after a restart on a new port the client follows the server.
    s = call(e2e::SharedChannel(server.address()), ctx);
    if (!Transient(s.error_code())) return s;
    ++*retries;
    std::this_thread::sleep_for(200ms);
  }
  return s;
}

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Resident set (MB) and open descriptors of `pid`; -1 when it is gone.
std::pair<double, int> Usage(pid_t pid) {
  if (pid <= 0) return {-1, -1};
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  double rss = -1;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) rss = std::atof(line.c_str() + 6) / 1024.0;
  }
  int fds = 0;
  std::error_code ec;
  for (auto it = fs::directory_iterator("/proc/" + std::to_string(pid) + "/fd", ec);
       !ec && it != fs::directory_iterator(); it.increment(ec))
    ++fds;
  return {rss, ec ? -1 : fds};
}

// Children of `pid` (the job processes of the server).
std::vector<pid_t> Children(pid_t pid) {
  std::vector<pid_t> out;
  if (DIR* d = opendir("/proc")) {
    while (dirent* e = readdir(d)) {
      const pid_t p = std::atoi(e->d_name);
      if (p <= 0) continue;
      const std::string stat = ReadFile("/proc/" + std::to_string(p) + "/stat");
      const size_t close = stat.rfind(')');
      if (close == std::string::npos) continue;
      std::istringstream rest(stat.substr(close + 2));
      char state;
      pid_t ppid = 0;
      rest >> state >> ppid;
      if (ppid == pid) out.push_back(p);
    }
    closedir(d);
  }
  return out;
}

json DirSize(const fs::path& root) {
  json by_entry = json::object();
  int64_t bytes = 0, files = 0;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(root, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    const int64_t size = static_cast<int64_t>(it->file_size(ec));
    bytes += size;
    ++files;
    const std::string top = fs::relative(it->path(), root, ec).begin()->string();
    if (!by_entry.contains(top)) by_entry[top] = {{"bytes", 0}, {"files", 0}};
    by_entry[top]["bytes"] = by_entry[top]["bytes"].get<int64_t>() + size;
    by_entry[top]["files"] = by_entry[top]["files"].get<int64_t>() + 1;
  }
  return {{"bytes", bytes}, {"files", files}, {"by_entry", by_entry}};
}

json Curve(const std::vector<std::array<double, 3>>& samples, int column) {
  json points = json::array();
  const size_t step = std::max<size_t>(1, samples.size() / 60);
  for (size_t i = 0; i < samples.size(); i += step)
    points.push_back({std::round(samples[i][0]), std::round(samples[i][column] * 10) / 10});
  if (!samples.empty()) points.push_back({std::round(samples.back()[0]), samples.back()[column]});
  return points;
}

// One tiny NIfTI whose bytes differ by `seed` (so each job uploads its own blob).
std::string TinyVolume(const fs::path& scratch, int seed) {
  const fs::path p = scratch / ("v" + std::to_string(seed) + ".nii");
  e2e::WriteTinyNifti(p, 12, 10, 8, seed % 30000);
  // Two more voxels make every seed distinct beyond the int16 of the first one.
  std::string bytes = ReadFile(p);
  fs::remove(p);
  std::memcpy(bytes.data() + 352 + 2, &seed, sizeof seed);
  return bytes;
}

std::string Sha(const std::string& bytes) {
  server::Sha256 h;
  h.Update(bytes.data(), bytes.size());
  return h.HexDigest();
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> const char* {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--jobs")
      o.jobs = std::atoi(next());
    else if (a == "--clients")
      o.clients = std::atoi(next());
    else if (a == "--workers")
      o.workers = std::atoi(next());
    else if (a == "--chaos-seconds")
      o.chaos_seconds = std::atof(next());
    else if (a == "--blob-grace-seconds")
      o.blob_grace_seconds = std::atof(next());
    else if (a == "--in-flight")
      o.in_flight = std::atoi(next());
    else if (a == "--timeout-seconds")
      o.timeout_seconds = std::atof(next());
    else if (a == "--keep")
      o.keep = true;
    else {
      std::fprintf(stderr,
                   "usage: decima-soak [--jobs N] [--clients M] [--workers W] "
                   "[--chaos-seconds S] [--in-flight K] [--blob-grace-seconds G] "
                   "[--timeout-seconds T] [--keep]\n");
      return 2;
    }
  }
  if (o.jobs < 1 || o.clients < 1 || o.workers < 1 || o.chaos_seconds <= 0 || o.in_flight < 1) {
    std::fprintf(stderr,
                 "--jobs, --clients, --workers, --chaos-seconds and --in-flight must be "
                 "positive\n");
    return 2;
  }
  const fs::path scratch =
      fs::temp_directory_path() / ("decima-soak-" + std::to_string(::getpid()));
  fs::create_directories(scratch);
  const fs::path data_dir = scratch / "data";
  const std::string run = std::to_string(::getpid()) + "-" + std::to_string(std::time(nullptr));

  ServerSlot server(
      data_dir, {"--workers", std::to_string(o.workers), "--drain-seconds", "2", "--lease-seconds",
                 "3", "--no-fsync", "--blob-grace-seconds", std::to_string(o.blob_grace_seconds)});
  // The empty size is measured with the server stopped, as the final one is (SQLite's WAL is
  // checkpointed into jobs.sqlite on a clean stop).
  server.Stop();
  const json empty = DirSize(data_dir);
  server.Start();

  std::atomic<bool> done{false};
  std::mutex samples_mu;
  std::vector<std::array<double, 3>> samples;  // t, rss MB, fds
  std::thread monitor([&] {
    while (!done) {
      auto [rss, fds] = Usage(server.pid());
      if (rss >= 0) {
        std::lock_guard<std::mutex> l(samples_mu);
        samples.push_back({Now(), rss, double(fds)});
      }
      std::this_thread::sleep_for(1s);
    }
  });

  std::atomic<int> sigterms{0}, sigkills{0}, worker_kills{0};
  std::atomic<bool> submitting{true};
  std::thread chaos([&] {
    int step = 0;
    double next = Now() + o.chaos_seconds;
    while (!done) {
      std::this_thread::sleep_for(100ms);
      if (Now() < next) continue;
      next = Now() + o.chaos_seconds;
      switch (step++ % 4) {
        case 0:
        case 2: {  // kill one job process
          auto kids = Children(server.pid());
          if (!kids.empty()) {
            ::kill(kids[step % kids.size()], SIGKILL);
            ++worker_kills;
          }
          break;
        }
        case 1:
          server.Restart(SIGTERM);
          ++sigterms;
          break;
        case 3:
          server.Restart(SIGKILL);
          ++sigkills;
          break;
      }
    }
  });

  // Each request i: upload its volume, create the volume and the job (idempotent request ids).
  std::vector<std::string> job_names(o.jobs), volume_names(o.jobs);
  std::atomic<int> next_job{0}, submit_errors{0};
  std::atomic<int64_t> retries{0};
  std::mutex errors_mu;
  std::vector<std::string> errors;
  auto note_error = [&](const std::string& e) {
    ++submit_errors;
    std::lock_guard<std::mutex> l(errors_mu);
    if (errors.size() < 10) errors.push_back(e);
  };
  std::vector<std::thread> clients;
  for (int c = 0; c < o.clients; ++c) {
    clients.emplace_back([&] {
      std::vector<std::string> mine;  // this client's unfinished jobs
      auto unfinished = [&] {
        std::vector<std::string> still;
        for (const auto& name : mine) {
          v1::GetJobRequest g;
          g.set_name(name);
          v1::Job j;
          grpc::Status s = Retry(
              server,
              [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
                return v1::Jobs::NewStub(ch)->GetJob(&ctx, g, &j);
              },
              &retries);
          if (s.ok() && (j.state() == v1::QUEUED || j.state() == v1::RUNNING))
            still.push_back(name);
        }
        mine = std::move(still);
        return mine.size();
      };
      for (int i; (i = next_job++) < o.jobs;) {
        // At most --in-flight unfinished jobs per client (bounded: the run's timeout).
        while (unfinished() >= size_t(o.in_flight) && Now() < o.timeout_seconds)
          std::this_thread::sleep_for(200ms);
        const std::string bytes = TinyVolume(scratch, i);
        const std::string sha = Sha(bytes);
        v1::Blob blob;
        grpc::Status s = Retry(
            server,
            [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
              auto w = v1::Uploads::NewStub(ch)->Upload(&ctx, &blob);
              v1::UploadRequest r;
              r.set_sha256(sha);
              r.set_size_bytes(bytes.size());
              r.set_data(bytes);
              w->Write(r);
              w->WritesDone();
              return w->Finish();
            },
            &retries);
        if (!s.ok()) {
          note_error("upload " + std::to_string(i) + ": " + s.error_message());
          continue;
        }
        v1::CreateVolumeRequest cv;
        cv.set_request_id("soak-volume-" + run + "-" + std::to_string(i));
        auto* f = cv.mutable_volume()->add_files();
        f->set_path("v.nii");
        f->set_blob("blobs/" + sha);
        v1::Volume vol;
        s = Retry(
            server,
            [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
              return v1::Volumes::NewStub(ch)->CreateVolume(&ctx, cv, &vol);
            },
            &retries);
        if (!s.ok()) {
          note_error("volume " + std::to_string(i) + ": " + s.error_message());
          continue;
        }
        volume_names[i] = vol.name();
        v1::CreateJobRequest cj;
        cj.set_request_id("soak-job-" + run + "-" + std::to_string(i));
        cj.mutable_spec()->set_volume(vol.name());
        cj.mutable_spec()->set_image_size(64);
        v1::Job job;
        s = Retry(
            server,
            [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
              return v1::Jobs::NewStub(ch)->CreateJob(&ctx, cj, &job);
            },
            &retries);
        if (!s.ok()) {
          note_error("job " + std::to_string(i) + ": " + s.error_message());
          continue;
        }
        job_names[i] = job.name();
        mine.push_back(job.name());
      }
    });
  }
  for (auto& t : clients) t.join();
  submitting = false;
  const double submitted_at = Now();

  // Every job listed, until none is QUEUED or RUNNING (or the timeout).
  std::vector<v1::Job> listed;
  auto list_all = [&] {
    listed.clear();
    std::string token;
    do {
      v1::ListJobsRequest req;
      req.set_page_size(1000);
      req.set_page_token(token);
      v1::ListJobsResponse resp;
      grpc::Status s = Retry(
          server,
          [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
            resp.Clear();
            return v1::Jobs::NewStub(ch)->ListJobs(&ctx, req, &resp);
          },
          &retries);
      if (!s.ok()) return false;
      for (auto& j : resp.jobs()) listed.push_back(j);
      token = resp.next_page_token();
    } while (!token.empty());
    return true;
  };
  bool settled = false;
  while (Now() < o.timeout_seconds) {
    if (list_all()) {
      settled = std::none_of(listed.begin(), listed.end(), [](const v1::Job& j) {
        return j.state() == v1::QUEUED || j.state() == v1::RUNNING;
      });
      if (settled) break;
    }
    std::this_thread::sleep_for(2s);
  }
  done = true;
  chaos.join();
  const double settled_at = Now();
  const json at_end = DirSize(data_dir);

  std::map<std::string, const v1::Job*> by_name;
  std::map<std::string, int> per_request;
  std::map<int, int> attempts;
  int succeeded = 0, failed = 0, cancelled = 0;
  std::vector<std::string> failures;
  for (const auto& j : listed) {
    by_name[j.name()] = &j;
    ++per_request[j.request_id()];
    ++attempts[j.attempts()];
    if (j.state() == v1::SUCCEEDED) ++succeeded;
    if (j.state() == v1::FAILED) {
      ++failed;
      if (failures.size() < 5) failures.push_back(j.name() + ": " + j.error().message());
    }
    if (j.state() == v1::CANCELLED) ++cancelled;
  }
  // Lost: a request whose job is missing from the list or did not end. A job that FAILED
  // because the soak killed its process (the server fails such a job: a killed child is taken
  // for an out-of-memory kill and not retried) is counted apart; any other failure is unexpected.
  int lost = 0, duplicated = 0, failed_by_kill = 0;
  for (int i = 0; i < o.jobs; ++i) {
    auto it = by_name.find(job_names[i]);
    if (job_names[i].empty() || it == by_name.end() || it->second->state() == v1::QUEUED ||
        it->second->state() == v1::RUNNING)
      ++lost;
  }
  for (const auto& j : listed) {
    if (j.state() == v1::FAILED &&
        j.error().message().find("killed by signal 9") != std::string::npos)
      ++failed_by_kill;
  }
  for (const auto& [request, n] : per_request) duplicated += n - 1;

  // Delete every job and volume; then the data dir should be back to its empty size.
  int delete_errors = 0;
  for (const auto& j : listed) {
    v1::DeleteJobRequest d;
    d.set_name(j.name());
    v1::DeleteJobResponse r;
    grpc::Status s = Retry(
        server,
        [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
          return v1::Jobs::NewStub(ch)->DeleteJob(&ctx, d, &r);
        },
        &retries);
    if (!s.ok()) ++delete_errors;
  }
  std::set<std::string> volumes(volume_names.begin(), volume_names.end());
  volumes.erase("");
  for (const auto& v : volumes) {
    v1::DeleteVolumeRequest d;
    d.set_name(v);
    v1::DeleteVolumeResponse r;
    grpc::Status s = Retry(
        server,
        [&](std::shared_ptr<grpc::Channel> ch, grpc::ClientContext& ctx) {
          return v1::Volumes::NewStub(ch)->DeleteVolume(&ctx, d, &r);
        },
        &retries);
    if (!s.ok()) ++delete_errors;
  }
  // The blob collector removes unused blobs once their grace has passed (it runs every quarter
  // of the grace, at least every second): wait for it, bounded.
  const double collect_until = Now() + 4 * o.blob_grace_seconds + 30;
  auto blobs_left = [&] {
    const json d = DirSize(data_dir / "blobs");
    return d["files"].get<int64_t>();
  };
  while (blobs_left() > 0 && Now() < collect_until) std::this_thread::sleep_for(500ms);
  done = true;
  monitor.join();
  auto [rss_end, fds_end] = Usage(server.pid());
  server.Stop();
  const json after_delete = DirSize(data_dir);

  json out;
  out["options"] = {{"jobs", o.jobs},
                    {"clients", o.clients},
                    {"workers", o.workers},
                    {"chaos_seconds", o.chaos_seconds},
                    {"in_flight_per_client", o.in_flight},
                    {"server_blob_grace_seconds", o.blob_grace_seconds},
                    {"volume", "12x10x8 int16 NIfTI, one distinct blob per job"}};
  out["jobs"] = {{"requested", o.jobs},
                 {"submitted", o.jobs - submit_errors.load()},
                 {"submit_errors", submit_errors.load()},
                 {"submit_error_examples", errors},
                 {"listed", listed.size()},
                 {"succeeded", succeeded},
                 {"failed", failed},
                 {"failed_because_the_soak_killed_the_job_process", failed_by_kill},
                 {"failed_unexpectedly", failed - failed_by_kill},
                 {"failure_examples", failures},
                 {"cancelled", cancelled},
                 {"lost", lost},
                 {"duplicated", duplicated},
                 {"settled", settled},
                 {"attempts_histogram", attempts},
                 {"client_retries", retries.load()}};
  out["chaos"] = {{"server_sigterm_restarts", sigterms.load()},
                  {"server_sigkill_restarts", sigkills.load()},
                  {"job_process_kills", worker_kills.load()}};
  out["seconds"] = {{"submit", submitted_at}, {"until_settled", settled_at}};
  out["jobs_per_minute"] = settled_at > 0 ? 60.0 * succeeded / settled_at : 0;
  {
    std::lock_guard<std::mutex> l(samples_mu);
    double rss_max = 0, fds_max = 0;
    for (const auto& s : samples) {
      rss_max = std::max(rss_max, s[1]);
      fds_max = std::max(fds_max, s[2]);
    }
    out["server"] = {{"rss_mb_curve", Curve(samples, 1)},
                     {"fds_curve", Curve(samples, 2)},
                     {"rss_mb_max", rss_max},
                     {"fds_max", fds_max},
                     {"rss_mb_end", rss_end},
                     {"fds_end", fds_end},
                     {"note", "a restart starts a new server process: RSS and fds restart"}};
  }
  out["data_dir"] = {
      {"empty", empty},
      {"at_end", at_end},
      {"after_deleting_everything", after_delete},
      {"delete_errors", delete_errors},
      {"growth_by_entry",
       [&] {
         json g = json::object();
         for (auto& [k, v] : after_delete["by_entry"].items()) {
           const int64_t before =
               empty["by_entry"].contains(k) ? empty["by_entry"][k]["bytes"].get<int64_t>() : 0;
           if (v["bytes"].get<int64_t>() != before) g[k] = v["bytes"].get<int64_t>() - before;
         }
         return g;
       }()},
      // The audit log is the record of every call, deletes included, and is rotated by size:
      // it is meant to grow, so it is reported above but not counted as data left behind.
      {"returns_to_empty", [&] {
         auto bytes = [](const json& d) {
           int64_t b = d["bytes"].get<int64_t>();
           // audit-<hostname>.log and its .lock (the default name since one writer per file).
           for (auto& [k, v] : d["by_entry"].items()) {
             if (k.rfind("audit", 0) == 0) b -= v["bytes"].get<int64_t>();
           }
           return b;
         };
         return bytes(after_delete) <= bytes(empty);
       }()}};
  std::printf("%s\n", out.dump(2).c_str());
  if (!o.keep) fs::remove_all(scratch);
  return (lost == 0 && duplicated == 0 && failed == failed_by_kill) ? 0 : 1;
}
