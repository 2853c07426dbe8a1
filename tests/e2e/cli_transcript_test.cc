// The CLI's words, kept: `decima --help` and every verb's `--help`, and what each verb prints
// (stdout, stderr and exit code, in its table and JSON forms) for a fixed job on a real server,
// compared with the golden transcripts in tests/e2e/cli_transcript/. What differs from run to
// run (ids, times, durations, digests, paths, ports) is masked, so any other change of the
// output fails here: moving code around the client must not change a byte of what users see.
// After an intended change of the output, rewrite the goldens with
//   DECIMA_UPDATE_GOLDEN=1 build/tests/e2e/cli_transcript_test
// and review the diff.
#include <algorithm>
#include <fstream>
#include <regex>
#include <set>
#include <sstream>

#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using namespace std::chrono_literals;

const fs::path kGoldenDir = fs::path(DECIMA_SOURCE_DIR) / "tests/e2e/cli_transcript";

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Builds a transcript: each command with its exit code, stdout and stderr, masked.
class Transcript {
 public:
  // Literal texts (paths, ids) replaced before the patterns run, longest first at Mask time.
  void Replace(const std::string& text, const std::string& with) {
    if (!text.empty()) literals_.emplace_back(text, with);
  }

  // `sorted`: the lines of stdout sorted after masking, for a listing ordered by ids.
  void Add(const std::string& shown, const CliResult& r, bool sorted = false) {
    text_ += "$ decima " + shown + "\n";
    text_ += "--- exit " + std::to_string(r.rc) + "\n";
    std::string out = Mask(r.out);
    if (sorted) {
      std::vector<std::string> lines;
      std::istringstream in(out);
      for (std::string l; std::getline(in, l);) lines.push_back(l);
      std::sort(lines.begin(), lines.end());
      out.clear();
      for (const auto& l : lines) out += l + "\n";
    }
    text_ += "--- stdout\n" + out;
    text_ += "--- stderr\n" + Mask(r.err);
    text_ += "\n";
  }

  std::string Mask(std::string s) {
    auto literals = literals_;
    std::sort(literals.begin(), literals.end(),
              [](const auto& a, const auto& b) { return a.first.size() > b.first.size(); });
    for (const auto& [from, to] : literals) {
      for (size_t at = s.find(from); at != std::string::npos; at = s.find(from, at + to.size())) {
        s.replace(at, from.size(), to);
      }
    }
    // The ids the server made, wherever they appear (tables show them without "jobs/", and an
    // id seen once in a name is masked in every later output).
    static const std::regex id_re(R"((jobs|volumes)/([0-9a-f]{16}))");
    for (std::sregex_iterator it(s.begin(), s.end(), id_re), end; it != end; ++it) {
      ids_.insert((*it)[2]);
    }
    for (const auto& id : ids_) {
      for (size_t at = s.find(id); at != std::string::npos; at = s.find(id, at)) {
        s.replace(at, id.size(), "<ID>");
      }
    }
    // What no run repeats: timestamps (local in tables, RFC 3339 in JSON), durations and
    // clocks, digests, request ids; and what the job's timing leaks into: the artifacts' sizes
    // (metrics.json holds the stage times, the pictures the job id), the number of progress
    // events (the level set's iterations), metrics.json itself.
    static const std::vector<std::pair<std::regex, std::string>> patterns = {
        {std::regex(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d+)?Z)"), "<TIMESTAMP>"},
        {std::regex(R"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d)"), "<TIME>"},
        {std::regex(R"([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})"), "<UUID>"},
        {std::regex(R"(\b[0-9a-f]{64}\b)"), "<SHA256>"},
        {std::regex(R"(\b[0-9a-f]{12}\b)"), "<SHA12>"},
        {std::regex(R"(\b\d+:\d\d(:\d\d)?\b)"), "<DURATION>"},
        {std::regex(R"(in \d+\.\d+ s\b)"), "in <SECONDS>"},
        {std::regex(R"(\b\d+(\.\d+)? (B|KB|MB|GB)\b)"), "<SIZE>"},
        {std::regex(R"(\b\d+(\.\d+)?x the input)"), "<RATIO>x the input"},
        {std::regex(R"("metrics_json":"(\\.|[^"\\])*")"), R"("metrics_json":"<METRICS>")"},
        {std::regex(R"re("(size_bytes|bytes|artifact_bytes|sequence|last_sequence)":"?\d+"?)re"),
         R"("$1":<N>)"},
    };
    for (const auto& [re, with] : patterns) s = std::regex_replace(s, re, with);
    // Progress events of a JSON watch, as many as the run made, become one line.
    static const std::regex progress_events(
        R"((\{"sequence":<N>,"time":"<TIMESTAMP>","progress":[^\n]*\n)+)");
    s = std::regex_replace(s, progress_events, "<PROGRESS EVENTS>\n");
    return s;
  }

  const std::string& text() const { return text_; }

 private:
  std::vector<std::pair<std::string, std::string>> literals_;
  std::set<std::string> ids_;
  std::string text_;
};

// Compares with the golden file, or rewrites it under DECIMA_UPDATE_GOLDEN=1.
void ExpectGolden(const std::string& name, const std::string& actual, const fs::path& scratch) {
  const fs::path golden = kGoldenDir / name;
  const char* update = std::getenv("DECIMA_UPDATE_GOLDEN");
  if (update != nullptr && std::string(update) == "1") {
    fs::create_directories(kGoldenDir);
    std::ofstream(golden, std::ios::binary) << actual;
    return;
  }
  ASSERT_TRUE(fs::exists(golden)) << golden << " is missing (DECIMA_UPDATE_GOLDEN=1 writes it)";
  const std::string expected = ReadFile(golden);
  if (expected == actual) return;
  const fs::path got = scratch / name;
  std::ofstream(got, std::ios::binary) << actual;
  const CliResult diff = RunProgram({"/usr/bin/diff", "-u", golden.string(), got.string()});
  ADD_FAILURE() << "the CLI's output differs from " << golden << ":\n" << diff.out;
}

class CliTranscript : public ScratchTest {
 protected:
  CliTranscript() : ScratchTest("cli_transcript") {}
};

TEST_F(CliTranscript, HelpOfTheProgramAndOfEveryVerb) {
  Transcript t;
  t.Replace(CliBinary().string(), "decima");
  const std::vector<std::vector<std::string>> commands = {{"--help"},
                                                          {"--version"},
                                                          {"submit", "--help"},
                                                          {"watch", "--help"},
                                                          {"status", "--help"},
                                                          {"describe", "--help"},
                                                          {"list", "--help"},
                                                          {"cancel", "--help"},
                                                          {"retry", "--help"},
                                                          {"fetch", "--help"},
                                                          {"delete", "--help"},
                                                          {"prune", "--help"},
                                                          {"health", "--help"},
                                                          {"version", "--help"},
                                                          {"pull", "--help"},
                                                          {"series", "--help"},
                                                          {"series", "delete", "--help"},
                                                          {},
                                                          {"frobnicate"},
                                                          {"list", "--bogus"}};
  for (const auto& args : commands) {
    std::vector<std::string> argv = {CliBinary().string()};
    argv.insert(argv.end(), args.begin(), args.end());
    std::string shown;
    for (const auto& a : args) shown += (shown.empty() ? "" : " ") + a;
    t.Add(shown, RunProgram(argv, 30s));
  }
  ExpectGolden("help.txt", t.text(), scratch_);
}

TEST_F(CliTranscript, EveryVerbOnAFixedJob) {
  ServerProcess server(scratch_ / "data");
  Transcript t;
  t.Replace(scratch_.string(), "<SCRATCH>");
  t.Replace(server.address(), "<SERVER>");
  auto run = [&](const std::vector<std::string>& args, bool sorted = false) {
    std::string shown;
    for (const auto& a : args) shown += (shown.empty() ? "" : " ") + t.Mask(a);
    CliResult r = RunCli(server.address(), args, 120s);
    t.Add(shown, r, sorted);
    return r;
  };
  const std::vector<std::string> job_options = {"--image-size", "32",        "--reduction",
                                                "0.3",          "--regions", "2"};
  std::vector<std::string> submit = {"-q", "submit", volume_.string()};
  submit.insert(submit.end(), job_options.begin(), job_options.end());
  submit.push_back("--watch");
  CliResult first = run(submit);
  ASSERT_EQ(first.rc, 0) << first.err << server.Log();
  const std::string job = FirstLine(first.out);
  // A second job, through a batch of one study, for the tables of several jobs. In JSON: the
  // table's INPUT column is the scratch path, whose length (and so the padding) varies; the
  // same table is printed by `watch J1 J2` below with display names.
  fs::create_directories(scratch_ / "studies" / "a");
  WriteTinyNifti(scratch_ / "studies" / "a" / "other.nii", 12, 10, 8, 1);
  std::vector<std::string> batch = {"-q", "submit", "--each", (scratch_ / "studies").string()};
  batch.insert(batch.end(), job_options.begin(), job_options.end());
  // Not --watch: the stream's first snapshot may find the job QUEUED or RUNNING.
  batch.insert(batch.end(), {"-o", "json"});
  CliResult second = run(batch);
  ASSERT_EQ(second.rc, 0) << second.err;
  // The batch's row: {"job":"jobs/ID",...}; watched by its short id.
  const size_t at = second.out.find("jobs/");
  ASSERT_NE(at, std::string::npos) << second.out;
  const std::string second_job = second.out.substr(at + 5, 16);
  ASSERT_EQ(RunCli(server.address(), {"-q", "watch", second_job}, 120s).rc, 0);

  run({"status", job});
  run({"describe", job, "-o", "json"});
  run({"list"});
  run({"list", "-o", "wide"});
  run({"list", "--json"});
  run({"list", "--page-size", "1"});
  run({"list", "--state", "running"});
  run({"list", "--state", "done"});
  run({"watch", job});
  run({"watch", job, "-o", "json"});
  run({"watch", job, second_job});
  run({"fetch", job, "--out", (scratch_ / "fetched").string()});
  run({"fetch", job, "--out", (scratch_ / "metrics").string(), "--only", "metrics", "-o", "json"});
  run({"fetch", job, "--out", (scratch_ / "none").string(), "--only", "nothing"});
  run({"series"});
  run({"series", "-o", "json"});
  run({"series", "delete", "1.2.3"});
  run({"health"});
  run({"health", "--json"});
  run({"version"});
  run({"version", "--json"});
  run({"cancel", job});
  run({"retry", job});
  run({"status", "zzzz"});
  // prune goes through jobs and volumes by name, and names are random: sorted.
  run({"prune"}, true);
  run({"prune", "--state", "running"});
  run({"prune", "--older-than", "soon"});
  run({"delete", job, "--volume"}, true);
  run({"prune", "--force", "-o", "json"}, true);
  run({"list"});
  ExpectGolden("verbs.txt", t.text(), scratch_);
}

}  // namespace
}  // namespace decima::e2e
