// decima-server's command line as a script meets it: --help lists the exit codes main()
// returns, and every usage mistake exits 2 (issue 33, part 4).
#include <fstream>
#include <sstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
using ::testing::HasSubstr;
using namespace std::chrono_literals;

TEST(ServerCommandLine, HelpListsTheExitCodes) {
  CliResult r = RunProgram({ServerBinary().string(), "--help"}, 30s);
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("Exit codes:"));
  EXPECT_THAT(r.out, HasSubstr("0  stopped by SIGTERM or SIGINT after draining"));
  EXPECT_THAT(r.out, HasSubstr("1  could not start"));
  EXPECT_THAT(r.out, HasSubstr("2  usage"));
}

// The whole --help text against the checked-in transcript, so that a change to the flags or
// their wording is a visible change to tests/e2e/testdata/decima-server-help.txt. The default
// --data-dir follows XDG_DATA_HOME, which is cleared; the usage line names the binary as run.
TEST(ServerCommandLine, HelpIsTheCheckedInTranscript) {
  const std::string binary = ServerBinary().string();
  CliResult r = RunProgram({binary, "--help"}, 30s, {{"XDG_DATA_HOME", ""}});
  ASSERT_EQ(r.rc, 0) << r.err;
  std::string help = r.out;
  const size_t at = help.find(binary);
  ASSERT_NE(at, std::string::npos) << help;
  help.replace(at, binary.size(), "decima-server");
  std::ifstream in(std::string(DECIMA_SOURCE_DIR) + "/tests/e2e/testdata/decima-server-help.txt");
  std::stringstream transcript;
  transcript << in.rdbuf();
  ASSERT_TRUE(in) << "cannot read the transcript";
  EXPECT_EQ(help, transcript.str());
}

TEST(ServerCommandLine, UsageMistakesExitTwoAndAnInvalidValueAtStartExitsOne) {
  // Unknown flag, value out of range, a named file that does not exist: CLI11 refuses them.
  for (const std::vector<std::string>& flags : {std::vector<std::string>{"--no-such-flag"},
                                                {"--workers", "0"},
                                                {"--tokens-file", "/nonexistent/tokens"}}) {
    std::vector<std::string> argv = {ServerBinary().string()};
    argv.insert(argv.end(), flags.begin(), flags.end());
    CliResult r = RunProgram(argv, 30s);
    EXPECT_EQ(r.rc, 2) << flags[0] << ": " << r.out << r.err;
  }
  // A value CLI11 accepts but main() checks: exit 1 naming the flag.
  const std::string data = (testing::MakeScratchDir("server_help") / "data").string();
  CliResult r =
      RunProgram({ServerBinary().string(), "--data-dir", data, "--store", "mysql://x"}, 30s);
  EXPECT_EQ(r.rc, 1) << r.out << r.err;
  EXPECT_THAT(r.out + r.err, HasSubstr("--store"));
}

}  // namespace
}  // namespace decima::e2e
