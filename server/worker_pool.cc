#include "server/worker_pool.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstring>
#include <fstream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "server/sha256.h"
#include "server/volume_probe.h"
#include "server/worker_process.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace fs = std::filesystem;
namespace {

using Clock = std::chrono::steady_clock;

int64_t MsSince(Clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - t).count();
}

// The last non-empty line of a log file (at most 300 bytes), for crash reports.
std::string LogTail(const fs::path& log) {
  std::ifstream in(log, std::ios::binary);
  if (!in) return {};
  in.seekg(0, std::ios::end);
  std::streamoff size = in.tellg();
  std::streamoff start = size > 300 ? size - 300 : 0;
  in.seekg(start);
  std::string s(static_cast<size_t>(size - start), '\0');
  in.read(s.data(), static_cast<std::streamsize>(s.size()));
  while (!s.empty() && (s.back() == '\n' || s.back() == '\r')) s.pop_back();
  size_t nl = s.rfind('\n');
  return nl == std::string::npos ? s : s.substr(nl + 1);
}

struct Child {
  pid_t pid = -1;
  int fd = -1;  // read end of the protocol pipe
};

absl::StatusOr<Child> Spawn(const WorkerPoolOptions& o, const fs::path& job_dir,
                            const fs::path& input, const fs::path& label_map,
                            const std::string& fault) {
  std::vector<std::string> args = {o.worker_exe.string(), "--run-job", job_dir.string(), "--input",
                                   input.string()};
  if (!label_map.empty()) {
    args.push_back("--label-map");
    args.push_back(label_map.string());
  }
  if (!fault.empty()) {
    args.push_back("--fault");
    args.push_back(fault);
  }
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  int p[2];
  if (::pipe2(p, O_CLOEXEC) != 0)
    return absl::InternalError(absl::StrCat("pipe: ", std::strerror(errno)));
  int log =
      ::open((job_dir / "worker.log").c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
  int devnull = ::open("/dev/null", O_RDONLY | O_CLOEXEC);
  pid_t parent = ::getpid();
  rlimit mem{};
  mem.rlim_cur = mem.rlim_max = static_cast<rlim_t>(o.worker_memory_mb) << 20;
  pid_t pid = ::fork();
  if (pid == 0) {
    // Child: async-signal-safe calls only until exec.
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);  // the server died: so does its job
    if (::getppid() != parent) ::_exit(127);
    sigset_t none;
    sigemptyset(&none);
    ::sigprocmask(SIG_SETMASK, &none, nullptr);  // the server blocks SIGTERM in its threads
    if (devnull >= 0) ::dup2(devnull, 0);
    if (log >= 0) {
      ::dup2(log, 1);
      ::dup2(log, 2);
    }
    if (p[1] == kWorkerFd) {
      ::fcntl(kWorkerFd, F_SETFD, 0);
    } else {
      ::dup2(p[1], kWorkerFd);
    }
    if (o.worker_memory_mb > 0) ::setrlimit(RLIMIT_AS, &mem);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  int err = errno;
  ::close(p[1]);
  if (log >= 0) ::close(log);
  if (devnull >= 0) ::close(devnull);
  if (pid < 0) {
    ::close(p[0]);
    return absl::InternalError(absl::StrCat("fork: ", std::strerror(err)));
  }
  return Child{pid, p[0]};
}

std::string SignalName(int sig) {
  const char* d = ::strsignal(sig);
  return absl::StrCat(sig, " (", d ? d : "?", ")");
}

}  // namespace

WorkerPool::WorkerPool(JobStore* store, WorkerPoolOptions options)
    : store_(store), options_(std::move(options)) {}

WorkerPool::~WorkerPool() { Drain(std::chrono::milliseconds(0)); }

void WorkerPool::Start() {
  for (int i = 0; i < options_.workers; ++i) slots_.push_back(std::make_unique<Slot>());
  for (int i = 0; i < options_.workers; ++i) threads_.emplace_back([this, i] { Loop(i); });
}

void WorkerPool::Notify() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    ++wakeups_;
  }
  cv_.notify_all();
}

void WorkerPool::Cancel(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mu_);
  for (auto& s : slots_) {
    if (s->job_id == job_id) s->cancel = true;
  }
}

void WorkerPool::Drain(std::chrono::milliseconds grace) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (stopping_ && threads_.empty()) return;
    stopping_ = true;
  }
  cv_.notify_all();
  auto deadline = Clock::now() + grace;
  while (running_.load() > 0 && Clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto& s : slots_) s->requeue = true;
  }
  for (auto& t : threads_) t.join();
  threads_.clear();
}

void WorkerPool::Loop(int index) {
  Slot& slot = *slots_[index];
  for (;;) {
    int64_t seen;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (stopping_) return;
      seen = wakeups_;
    }
    auto claimed = store_->ClaimNext(options_.owner, options_.lease_ms);
    if (!claimed.ok()) {
      spdlog::error("worker {}: claiming a job: {}", index, claimed.status().ToString());
    } else if (claimed->has_value()) {
      const v1::Job& job = **claimed;
      {
        std::lock_guard<std::mutex> lock(mu_);
        slot.job_id = job.name().substr(5);
        slot.cancel = false;
        slot.requeue = false;
      }
      running_.fetch_add(1);
      RunOne(slot, job);
      running_.fetch_sub(1);
      {
        std::lock_guard<std::mutex> lock(mu_);
        slot.job_id.clear();
      }
      continue;
    }
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait_for(lock, std::chrono::seconds(1), [&] { return stopping_ || wakeups_ != seen; });
  }
}

void WorkerPool::RunOne(Slot& slot, const v1::Job& job) {
  const std::string id = job.name().substr(5);
  const auto t0 = Clock::now();
  double queued_s = static_cast<double>(job.start_time().seconds() - job.create_time().seconds()) +
                    (job.start_time().nanos() - job.create_time().nanos()) * 1e-9;
  spdlog::info("job {} RUNNING attempt {} (queued {:.3f} s)", id, job.attempts(), queued_s);

  auto fail = [&](int code, const std::string& message) {
    v1::Job outcome;
    outcome.mutable_error()->set_code(code);
    outcome.mutable_error()->set_message(message);
    auto r = store_->Finish(id, options_.owner, v1::FAILED, outcome);
    if (!r.ok()) spdlog::error("job {}: recording failure: {}", id, r.status().ToString());
    spdlog::info("job {} FAILED after {:.3f} s: {}", id, MsSince(t0) / 1000.0, message);
  };

  // Prepare the job folder: a fresh out/ for every attempt.
  fs::path dir = options_.data_dir.job_dir(id);
  std::error_code ec;
  fs::remove_all(dir / "out", ec);
  fs::create_directories(dir / "out", ec);
  if (ec) return fail(13, absl::StrCat("creating ", (dir / "out").string(), ": ", ec.message()));
  {
    std::ofstream spec(dir / "spec.pb", std::ios::binary | std::ios::trunc);
    spec << job.spec().SerializeAsString();
    if (!spec) return fail(13, absl::StrCat("writing ", (dir / "spec.pb").string()));
  }
  auto resolve = [&](const std::string& volume_name, fs::path* out) -> absl::Status {
    auto vid = ParseName(volume_name, "volumes", "spec.volume");
    if (!vid.ok()) return vid.status();
    auto vol = store_->GetVolume(*vid);
    if (!vol.ok()) return vol.status();
    *out = VolumeInput(options_.data_dir.volume_files(*vid), *vol);
    return absl::OkStatus();
  };
  fs::path input, label_map;
  absl::Status rs = resolve(job.spec().volume(), &input);
  if (rs.ok() && !job.spec().label_map().empty()) rs = resolve(job.spec().label_map(), &label_map);
  if (!rs.ok()) return fail(static_cast<int>(rs.code()), std::string(rs.message()));

  const std::string fault = options_.allow_faults ? options_.data_dir.ReadJobFault(id) : "";
  auto child = Spawn(options_, dir, input, label_map, fault);
  if (!child.ok()) return fail(13, std::string(child.status().message()));

  // Relay the child's lines until it closes the pipe, renewing the lease and watching cancel.
  std::string buf, stage = "start";
  nlohmann::json final_line;
  bool lost_lease = false, term_sent = false, kill_sent = false;
  Clock::time_point term_at{}, last_renew = Clock::now(), last_poll = Clock::now(), last_progress{};
  std::string last_stored_stage;
  auto handle_line = [&](const std::string& line) {
    nlohmann::json j = nlohmann::json::parse(line, nullptr, /*allow_exceptions=*/false);
    if (!j.is_object()) return;
    std::string type = j.value("type", "");
    if (type == "progress") {
      v1::Progress p;
      p.set_stage(j.value("stage", ""));
      p.set_fraction(j.value("fraction", 0.0));
      p.set_message(j.value("message", ""));
      if (j.contains("metrics") && j["metrics"].is_object()) {
        for (auto& [k, v] : j["metrics"].items()) {
          if (v.is_number()) (*p.mutable_metrics())[k] = v.get<double>();
        }
      }
      stage = p.stage();
      bool due = p.stage() != last_stored_stage || p.fraction() >= 1.0 ||
                 MsSince(last_progress) >= options_.progress_interval_ms;
      if (due) {
        absl::Status s = store_->AppendProgress(id, options_.owner, p);
        if (!s.ok()) spdlog::warn("job {}: storing progress: {}", id, s.ToString());
        last_stored_stage = p.stage();
        last_progress = Clock::now();
      }
    } else if (type == "result" || type == "error") {
      final_line = std::move(j);
    }
  };
  for (;;) {
    pollfd pfd{child->fd, POLLIN, 0};
    int pr = ::poll(&pfd, 1, 50);
    if (pr > 0) {
      char tmp[65536];
      ssize_t n = ::read(child->fd, tmp, sizeof tmp);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) break;
      buf.append(tmp, static_cast<size_t>(n));
      size_t pos;
      while ((pos = buf.find('\n')) != std::string::npos) {
        handle_line(buf.substr(0, pos));
        buf.erase(0, pos + 1);
      }
      if (buf.size() > (16u << 20)) buf.clear();  // a runaway line: drop it
    }
    if (MsSince(last_renew) >= options_.lease_ms / 3) {
      last_renew = Clock::now();
      absl::Status s = store_->RenewLease(id, options_.owner, options_.lease_ms);
      if (!s.ok()) {
        spdlog::warn("job {}: {}; stopping its worker", id, s.ToString());
        lost_lease = true;
      }
    }
    if (MsSince(last_poll) >= 500) {
      last_poll = Clock::now();
      auto c = store_->CancelRequested(id);
      if (c.ok() && *c) slot.cancel = true;
    }
    if ((slot.cancel || slot.requeue || lost_lease) && !term_sent) {
      ::kill(child->pid, SIGTERM);
      term_sent = true;
      term_at = Clock::now();
    }
    if (term_sent && !kill_sent && MsSince(term_at) >= options_.cancel_grace_ms) {
      ::kill(child->pid, SIGKILL);
      kill_sent = true;
    }
  }
  ::close(child->fd);
  int wstatus = 0;
  for (;;) {
    pid_t r = ::waitpid(child->pid, &wstatus, WNOHANG);
    if (r == child->pid || (r < 0 && errno != EINTR)) break;
    if ((slot.cancel || slot.requeue || lost_lease) && !term_sent) {
      ::kill(child->pid, SIGTERM);
      term_sent = true;
      term_at = Clock::now();
    }
    if (term_sent && !kill_sent && MsSince(term_at) >= options_.cancel_grace_ms) {
      ::kill(child->pid, SIGKILL);
      kill_sent = true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  const double secs = MsSince(t0) / 1000.0;

  if (lost_lease) return;  // another owner holds the job now
  if (slot.cancel) {
    v1::Job outcome;
    outcome.mutable_error()->set_code(1);
    outcome.mutable_error()->set_message(absl::StrCat("cancelled by request during ", stage));
    auto r = store_->Finish(id, options_.owner, v1::CANCELLED, outcome);
    if (!r.ok()) spdlog::error("job {}: recording cancel: {}", id, r.status().ToString());
    spdlog::info("job {} CANCELLED after {:.3f} s in stage {}", id, secs, stage);
    return;
  }
  if (slot.requeue) {
    auto r = store_->Requeue(id, options_.owner, "requeued: the server shut down while it ran");
    if (!r.ok()) spdlog::error("job {}: requeue: {}", id, r.status().ToString());
    spdlog::info("job {} QUEUED again after {:.3f} s (server shutting down)", id, secs);
    return;
  }
  bool exited = WIFEXITED(wstatus);
  int code = exited ? WEXITSTATUS(wstatus) : -1;
  if (final_line.is_object() && final_line.value("type", "") == "result" && exited &&
      code == kWorkerExitOk) {
    v1::Job outcome;
    fs::path out_dir = fs::weakly_canonical(dir / "out", ec);
    for (const auto& a : final_line.value("artifacts", nlohmann::json::array())) {
      std::string name = a.value("name", "");
      fs::path path = fs::weakly_canonical(fs::path(a.value("path", "")), ec);
      // Only plain names of files inside out/ are served.
      if (name.empty() || name.find('/') != std::string::npos || name[0] == '.' ||
          path.parent_path() != out_dir || !fs::is_regular_file(path, ec)) {
        return fail(13, absl::StrCat("pipeline returned artifact '", name, "' at ", path.string(),
                                     ", not a file in ", out_dir.string()));
      }
      auto sha = Sha256OfFile(path);
      if (!sha.ok()) return fail(13, std::string(sha.status().message()));
      auto* art = outcome.add_artifacts();
      art->set_name(absl::StrCat(job.name(), "/artifacts/", name));
      art->set_file_name(name);
      art->set_size_bytes(static_cast<int64_t>(fs::file_size(path, ec)));
      art->set_sha256(*sha);
    }
    outcome.set_metrics_json(final_line.value("metrics_json", ""));
    auto r = store_->Finish(id, options_.owner, v1::SUCCEEDED, outcome);
    if (!r.ok()) spdlog::error("job {}: recording success: {}", id, r.status().ToString());
    spdlog::info("job {} SUCCEEDED in {:.3f} s ({} artifacts)", id, secs, outcome.artifacts_size());
    return;
  }
  if (final_line.is_object() && final_line.value("type", "") == "error") {
    return fail(final_line.value("code", 2), final_line.value("message", "pipeline error"));
  }
  std::string why =
      exited ? absl::StrCat("the worker exited with code ", code)
             : absl::StrCat("the worker was killed by signal ", SignalName(WTERMSIG(wstatus)));
  if (!exited && WTERMSIG(wstatus) == SIGKILL) absl::StrAppend(&why, ", e.g. out of memory");
  absl::StrAppend(&why, " during stage ", stage);
  std::string tail = LogTail(dir / "worker.log");
  if (!tail.empty()) absl::StrAppend(&why, "; last log line: ", tail);
  fail(13, why);
}

}  // namespace decima::server
