// A real PostgreSQL server for tests and benchmarks: Debian's PostgreSQL 15 binaries, a cluster
// made by initdb in a fresh folder under /tmp, `postgres` started on a free loopback port and
// stopped by its PID. PostgreSQL refuses to run as root, so as root the folder is given to the
// `postgres` user and every PostgreSQL program runs as that user (setpriv, which execs, so the
// PID we hold is the postmaster's).
// Thread-safety: one object per thread; Sql() may be called from several threads.
#pragma once

#include <sys/types.h>

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace decima::testing {

class PostgresServer {
 public:
  // The folder of initdb/postgres/pg_isready, or nullopt when PostgreSQL is not installed
  // (callers GTEST_SKIP with WhyAbsent()).
  static std::optional<std::filesystem::path> BinDir();
  static std::string WhyAbsent();

  // initdb + start. `durable` false turns fsync off (tests); true keeps PostgreSQL's defaults
  // (benchmarks). Empty error() on success.
  explicit PostgresServer(bool durable = false);
  ~PostgresServer();  // Stop() and remove the folder

  const std::string& error() const { return error_; }
  int port() const { return port_; }
  pid_t pid() const { return pid_; }
  // postgresql://postgres@127.0.0.1:PORT/`db`
  std::string Dsn(const std::string& db = "postgres") const;

  // Creates database `name` (empty error on success).
  std::string CreateDatabase(const std::string& name);
  // Runs `sql` through psql in `db`; the unaligned output, or nullopt on failure.
  std::optional<std::string> Sql(const std::string& sql, const std::string& db = "postgres") const;

  // Fast shutdown (SIGINT to the postmaster, SIGKILL after 20 s) and start again on the same
  // port and data (what a restart of the database looks like to its clients).
  void Stop();
  std::string Start();

 private:
  std::string RunAsOwner(const std::vector<std::string>& argv, const std::string& log) const;

  std::filesystem::path bin_, dir_;
  bool as_postgres_ = false, durable_ = false;
  int port_ = 0;
  pid_t pid_ = -1;
  std::string error_;
};

}  // namespace decima::testing
