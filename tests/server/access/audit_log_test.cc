// AuditLog: each line names the caller, fields are bounded and escaped, refused unidentified
// calls are rate limited, a line that cannot be written stops mutations, one writer per file.
#include "server/access/audit_log.h"

#include <unistd.h>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;

std::vector<std::string> Lines(const fs::path& file) {
  std::ifstream in(file);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

std::shared_ptr<AuditLog> OpenLog(const fs::path& file) {
  auto log = AuditLog::Open(file.string(), 1 << 20, 2);
  EXPECT_TRUE(log.ok()) << log.status();
  return log.ok() ? *log : nullptr;
}

TEST(AuditLog, ARecordNamesTheCallerTheRpcTheResourceAndTheCodeOnly) {
  const fs::path file = testing::MakeScratchDir("audit") / "audit.log";
  auto log = OpenLog(file);
  ASSERT_NE(log, nullptr);
  const Principal alice{"alice", Role::kSubmitter};
  const grpc::Status refused(grpc::StatusCode::PERMISSION_DENIED, "secret message text");
  const grpc::Status returned = log->Record(&alice, "DeleteJob", "jobs/j1", refused);
  EXPECT_EQ(returned.error_code(), grpc::StatusCode::PERMISSION_DENIED);
  log->RecordSystem("dicom:CT1", "DicomQueueJob", "jobs/j2", absl::OkStatus(), "assoc-7");
  const auto lines = Lines(file);
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_THAT(lines[0], HasSubstr(R"({"principal":"alice","role":"submitter","rpc":"DeleteJob",)"
                                  R"("resource":"jobs/j1","result":"PERMISSION_DENIED"})"));
  EXPECT_THAT(lines[0], Not(HasSubstr("secret message text")));
  EXPECT_THAT(lines[1], HasSubstr(R"("principal":"dicom:CT1","role":"system")"));
  EXPECT_THAT(lines[1], HasSubstr(R"("association":"assoc-7","result":"OK")"));
}

TEST(AuditLog, FieldsAreCutAtTheLimitAndEscapedSoALineStaysOneLine) {
  const fs::path file = testing::MakeScratchDir("audit") / "audit.log";
  auto log = OpenLog(file);
  ASSERT_NE(log, nullptr);
  const Principal odd{"ev\"il\\\n\x7f\xc3\xa9", Role::kAdmin};
  const std::string long_resource = "jobs/" + std::string(AuditLog::kMaxField + 95, 'x');
  log->Record(&odd, "CreateJob", long_resource, grpc::Status::OK);
  const auto lines = Lines(file);
  ASSERT_EQ(lines.size(), 1u) << "a newline in a field must not start a new line";
  EXPECT_THAT(lines[0], HasSubstr(R"("principal":"ev\"il\\\u000a\u007f\u00c3\u00a9")"));
  const std::string kept = "jobs/" + std::string(AuditLog::kMaxField - 5, 'x');
  EXPECT_THAT(lines[0], HasSubstr("\"resource\":\"" + kept + "...(+100 bytes)\""));
  for (char c : lines[0]) {
    EXPECT_TRUE(c >= 0x20 && c < 0x7f) << "byte " << static_cast<int>(c) << " in " << lines[0];
  }
}

TEST(AuditLog, UnidentifiedFailuresAreRateLimitedAndTheDroppedCountIsReported) {
  const fs::path file = testing::MakeScratchDir("audit") / "audit.log";
  auto log = OpenLog(file);
  ASSERT_NE(log, nullptr);
  const grpc::Status unauth(grpc::StatusCode::UNAUTHENTICATED, "no token");
  // Start at the beginning of a second so that the burst falls in one window.
  const time_t start = std::time(nullptr);
  while (std::time(nullptr) == start) usleep(1000);
  const time_t window = std::time(nullptr);
  const int burst = 3 * AuditLog::kUnidentifiedPerSecond;
  for (int i = 0; i < burst; ++i) log->Record(nullptr, "CreateJob", "jobs/attacker", unauth);
  ASSERT_EQ(std::time(nullptr), window) << "the burst took a whole second; too loaded to tell";
  auto lines = Lines(file);
  ASSERT_EQ(lines.size(), static_cast<size_t>(AuditLog::kUnidentifiedPerSecond));
  EXPECT_THAT(lines[0], HasSubstr(R"({"principal":"","role":"","rpc":"CreateJob",)"
                                  R"("resource":"","result":"UNAUTHENTICATED"})"))
      << "nothing an unidentified caller sent is written";
  // An identified caller is never limited.
  const Principal bob{"bob", Role::kReader};
  log->Record(&bob, "CancelJob", "jobs/b", grpc::Status::OK);
  EXPECT_EQ(Lines(file).size(), static_cast<size_t>(AuditLog::kUnidentifiedPerSecond) + 1);
  while (std::time(nullptr) == window) usleep(1000);
  log->Record(nullptr, "CreateJob", "", unauth);
  lines = Lines(file);
  ASSERT_EQ(lines.size(), static_cast<size_t>(AuditLog::kUnidentifiedPerSecond) + 2);
  EXPECT_THAT(lines.back(),
              HasSubstr(",\"unidentified_dropped\":" +
                        std::to_string(burst - AuditLog::kUnidentifiedPerSecond) + "}"));
}

TEST(AuditLog, ARecordThatCannotBeWrittenRefusesFurtherMutations) {
  // As root a read-only directory is still writable; /dev/full fails every write with ENOSPC,
  // a full disk.
  if (!fs::exists("/dev/full")) GTEST_SKIP() << "/dev/full is missing";
  const fs::path dir = testing::MakeScratchDir("audit");
  const fs::path file = dir / "audit.log";
  fs::create_symlink("/dev/full", file);
  auto log = OpenLog(file);
  ASSERT_NE(log, nullptr);
  EXPECT_TRUE(log->Ready().ok()) << "nothing failed yet";
  const Principal alice{"alice", Role::kAdmin};
  log->Record(&alice, "DeleteVolume", "volumes/v", grpc::Status::OK);
  const grpc::Status ready = log->Ready();
  EXPECT_EQ(ready.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(ready.error_message(), HasSubstr("audit log cannot be written"));
  EXPECT_THAT(ready.error_message(), HasSubstr(file.string())) << "names the file";
  EXPECT_EQ(log->Ready().error_code(), grpc::StatusCode::UNAVAILABLE) << "it stays stopped";
}

TEST(AuditLog, AWrittenRecordKeepsMutationsAllowed) {
  const fs::path file = testing::MakeScratchDir("audit") / "audit.log";
  auto log = OpenLog(file);
  ASSERT_NE(log, nullptr);
  const Principal alice{"alice", Role::kAdmin};
  log->Record(&alice, "DeleteVolume", "volumes/v", grpc::Status::OK);
  EXPECT_TRUE(log->Ready().ok());
}

TEST(AuditLog, ASecondWriterOfTheSameFileIsRefused) {
  const fs::path file = testing::MakeScratchDir("audit") / "audit.log";
  auto first = OpenLog(file);
  ASSERT_NE(first, nullptr);
  auto second = AuditLog::Open(file.string(), 1 << 20, 2);
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(second.status().message()), HasSubstr(file.string()));
  first.reset();  // the lock goes with the writer
  EXPECT_TRUE(AuditLog::Open(file.string(), 1 << 20, 2).ok());
}

TEST(AuditLog, TheDefaultFileIsNamedForTheHostAndNumberedForFurtherServers) {
  char host[256] = {};
  ASSERT_EQ(::gethostname(host, sizeof host - 1), 0);
  std::string h(host);
  for (char& c : h) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '.') c = '_';
  }
  EXPECT_EQ(DefaultAuditPath("/d", 1), "/d/audit-" + h + ".log");
  EXPECT_EQ(DefaultAuditPath("/d", 2), "/d/audit-" + h + "-2.log");
  EXPECT_EQ(DefaultAuditPath("/d", 3), "/d/audit-" + h + "-3.log");
  EXPECT_NE(DefaultAuditPath("/d", 1), DefaultAuditPath("/d", 2));
}

}  // namespace
}  // namespace decima::server
