// One real PostgreSQL server per test program (initdb takes seconds), started on first use, and
// a fresh database per test.
#pragma once

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <memory>
#include <string>

#include "gtest/gtest.h"
#include "server/store/job_store.h"
#include "tests/testing/postgres_server.h"

namespace decima::server {

inline testing::PostgresServer* SharedPostgres() {
  static testing::PostgresServer* server = [] {
    auto* s = new testing::PostgresServer();
    std::atexit([] { delete SharedPostgres(); });
    return s;
  }();
  return server;
}

// A fresh database on the shared server: its DSN, or "" (with a test failure) if that failed.
inline std::string FreshDatabase() {
  static std::atomic<int> counter{0};
  auto* pg = SharedPostgres();
  if (!pg->error().empty()) return "";
  const std::string name = "t" + std::to_string(::getpid()) + "_" + std::to_string(counter++);
  std::string err = pg->CreateDatabase(name);
  EXPECT_EQ(err, "");
  return err.empty() ? pg->Dsn(name) : "";
}

inline absl::StatusOr<std::unique_ptr<JobStore>> OpenPostgres(const std::string& dsn,
                                                              int connections = 4) {
  PostgresStoreOptions o;
  o.connections = connections;
  o.reconnect_timeout = std::chrono::seconds(20);
  return OpenPostgresJobStore(dsn, o);
}

}  // namespace decima::server

// Skips the test when PostgreSQL is not installed; fails it if the server did not start.
#define DECIMA_REQUIRE_POSTGRES()                                                     \
  do {                                                                                \
    if (!::decima::testing::PostgresServer::BinDir()) {                               \
      GTEST_SKIP() << ::decima::testing::PostgresServer::WhyAbsent();                 \
    }                                                                                 \
    ASSERT_EQ(::decima::server::SharedPostgres()->error(), "") << "PostgreSQL start"; \
  } while (0)
