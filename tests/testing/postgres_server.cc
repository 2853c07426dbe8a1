#include "tests/testing/postgres_server.h"

#include <pwd.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <fstream>
#include <sstream>
#include <thread>

#include "tests/testing/process.h"

namespace decima::testing {
namespace fs = std::filesystem;
namespace {

std::string ReadText(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

}  // namespace

std::optional<fs::path> PostgresServer::BinDir() {
  for (const char* d :
       {"/usr/lib/postgresql/15/bin", "/usr/lib/postgresql/16/bin", "/usr/lib/postgresql/17/bin"}) {
    std::error_code ec;
    if (fs::exists(fs::path(d) / "initdb", ec) && fs::exists(fs::path(d) / "postgres", ec)) {
      return fs::path(d);
    }
  }
  return std::nullopt;
}

std::string PostgresServer::WhyAbsent() {
  return "PostgreSQL is not installed (no initdb under /usr/lib/postgresql/*/bin); "
         "deploy/install-deps.sh installs the Debian package postgresql";
}

PostgresServer::PostgresServer(bool durable) : durable_(durable) {
  auto bin = BinDir();
  if (!bin) {
    error_ = WhyAbsent();
    return;
  }
  bin_ = *bin;
  char tmpl[] = "/tmp/decima-pg-XXXXXX";
  if (::mkdtemp(tmpl) == nullptr) {
    error_ = "mkdtemp failed";
    return;
  }
  dir_ = tmpl;
  as_postgres_ = ::geteuid() == 0;
  if (as_postgres_) {
    passwd* pw = ::getpwnam("postgres");
    if (pw == nullptr) {
      error_ = "running as root and there is no 'postgres' user to run PostgreSQL as";
      return;
    }
    if (::chown(dir_.c_str(), pw->pw_uid, pw->pw_gid) != 0) {
      error_ = "chown of " + dir_.string() + " to postgres failed";
      return;
    }
  }
  error_ = RunAsOwner({(bin_ / "initdb").string(), "-D", (dir_ / "data").string(), "-U", "postgres",
                       "--auth=trust", "-E", "UTF8", "--no-sync"},
                      (dir_ / "initdb.log").string());
  if (!error_.empty()) return;
  port_ = FreePort();
  error_ = Start();
}

PostgresServer::~PostgresServer() {
  Stop();
  std::error_code ec;
  if (!dir_.empty()) fs::remove_all(dir_, ec);
}

std::string PostgresServer::RunAsOwner(const std::vector<std::string>& argv,
                                       const std::string& log) const {
  std::vector<std::string> full;
  if (as_postgres_) {
    full = {"/usr/bin/setpriv", "--reuid=postgres", "--regid=postgres", "--init-groups", "--"};
  }
  full.insert(full.end(), argv.begin(), argv.end());
  pid_t pid = Spawn(full, log);
  int rc = WaitExit(pid, std::chrono::seconds(120));
  if (rc != 0) {
    return argv[0] + " failed (exit " + std::to_string(rc) + "): " + ReadText(log);
  }
  return {};
}

std::string PostgresServer::Start() {
  if (pid_ > 0) return {};
  std::vector<std::string> argv;
  if (as_postgres_) {
    argv = {"/usr/bin/setpriv", "--reuid=postgres", "--regid=postgres", "--init-groups", "--"};
  }
  std::vector<std::string> pg = {(bin_ / "postgres").string(),
                                 "-D",
                                 (dir_ / "data").string(),
                                 "-c",
                                 "listen_addresses=127.0.0.1",
                                 "-p",
                                 std::to_string(port_),
                                 "-k",
                                 dir_.string(),
                                 "-c",
                                 "max_connections=200",
                                 "-c",
                                 "shared_buffers=32MB"};
  if (!durable_) {
    for (const char* o : {"fsync=off", "synchronous_commit=off", "full_page_writes=off"}) {
      pg.push_back("-c");
      pg.push_back(o);
    }
  }
  argv.insert(argv.end(), pg.begin(), pg.end());
  pid_ = Spawn(argv, (dir_ / "postgres.log").string());
  if (pid_ <= 0) return "postgres could not be started: " + argv[0];
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (std::chrono::steady_clock::now() < until) {
    int st = 0;
    if (::waitpid(pid_, &st, WNOHANG) == pid_) {
      pid_ = -1;
      return "postgres exited at start: " + ReadText(dir_ / "postgres.log");
    }
    pid_t p = Spawn(
        {(bin_ / "pg_isready").string(), "-q", "-h", "127.0.0.1", "-p", std::to_string(port_)},
        "/dev/null");
    if (WaitExit(p, std::chrono::seconds(10)) == 0) return {};
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  return "postgres did not accept connections within 60 s: " + ReadText(dir_ / "postgres.log");
}

void PostgresServer::Stop() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGINT);  // fast shutdown: clients are disconnected
  if (WaitExit(pid_, std::chrono::seconds(20)) < 0) ::kill(pid_, SIGKILL);
  pid_ = -1;
}

std::string PostgresServer::Dsn(const std::string& db) const {
  return "postgresql://postgres@127.0.0.1:" + std::to_string(port_) + "/" + db;
}

std::string PostgresServer::CreateDatabase(const std::string& name) {
  auto r = Sql("CREATE DATABASE " + name);
  return r ? std::string() : "CREATE DATABASE " + name + " failed";
}

std::optional<std::string> PostgresServer::Sql(const std::string& sql,
                                               const std::string& db) const {
  const fs::path out =
      dir_ / ("psql-" + std::to_string(::getpid()) + "-" +
              std::to_string(std::hash<std::thread::id>()(std::this_thread::get_id())) + ".out");
  pid_t p = Spawn(
      {"/usr/bin/psql", "-X", "-q", "-A", "-t", "-v", "ON_ERROR_STOP=1", "-d", Dsn(db), "-c", sql},
      out.string());
  const int rc = WaitExit(p, std::chrono::seconds(60));
  std::string text = ReadText(out);
  std::error_code ec;
  fs::remove(out, ec);
  if (rc != 0) return std::nullopt;
  while (!text.empty() && (text.back() == '\n')) text.pop_back();
  return text;
}

}  // namespace decima::testing
