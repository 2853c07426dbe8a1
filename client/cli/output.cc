#include "client/cli/output.h"

#include <google/protobuf/util/json_util.h>
#include <sys/ioctl.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <map>

#include "client/text.h"

namespace decima::client {

std::string ToJson(const google::protobuf::Message& m) {
  std::string out;
  google::protobuf::util::JsonPrintOptions o;
  o.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(m, &out, o);
  return out;
}

std::string JsonString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", c);
      out += buf;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

std::string ShortId(const std::string& name) {
  return name.rfind("jobs/", 0) == 0 ? name.substr(5) : name;
}

std::string FormatTime(const google::protobuf::Timestamp& t) {
  if (t.seconds() == 0) return "-";
  std::time_t secs = static_cast<std::time_t>(t.seconds());
  std::tm tm{};
  localtime_r(&secs, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", &tm);
  return buf;
}

std::string Percent(double f, int decimals) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.*f%%", decimals, 100 * f);
  return buf;
}

double SecondsSince(const google::protobuf::Timestamp& t) {
  if (t.seconds() == 0 && t.nanos() == 0) return -1;
  const auto now = std::chrono::system_clock::now().time_since_epoch();
  return std::chrono::duration<double>(now).count() - (t.seconds() + t.nanos() / 1e9);
}

double Between(const google::protobuf::Timestamp& a, const google::protobuf::Timestamp& b) {
  if (a.seconds() == 0 || b.seconds() == 0) return -1;
  return (b.seconds() - a.seconds()) + (b.nanos() - a.nanos()) / 1e9;
}

double JobSeconds(const v1::Job& j) {
  if (j.start_time().seconds() == 0) return -1;
  if (j.end_time().seconds() != 0) return Between(j.start_time(), j.end_time());
  return SecondsSince(j.start_time());
}

int TerminalColumns() {
  struct winsize ws {};
  if (::ioctl(2, TIOCGWINSZ, &ws) == 0 && ws.ws_col > 20) return ws.ws_col;
  return 100;
}

// Every cell is passed through TerminalSafe: names and messages come from the server (issue 35
// part 7: a display name with escape sequences reached an admin's terminal).
void PrintTable(const std::vector<std::vector<std::string>>& raw_rows) {
  std::vector<std::vector<std::string>> rows = raw_rows;
  for (auto& r : rows) {
    for (auto& cell : r) cell = TerminalSafe(cell);
  }
  std::vector<size_t> width;
  for (const auto& r : rows) {
    if (width.size() < r.size()) width.resize(r.size(), 0);
    for (size_t c = 0; c < r.size(); ++c) width[c] = std::max(width[c], r[c].size());
  }
  for (const auto& r : rows) {
    std::string line;
    for (size_t c = 0; c < r.size(); ++c) {
      line += r[c];
      if (c + 1 < r.size()) line.append(width[c] - r[c].size() + 3, ' ');
    }
    std::printf("%s\n", line.c_str());
  }
}

bool ContinueListing(const CliContext& ctx, const std::string& next_page_token, bool all) {
  if (next_page_token.empty()) return false;
  if (all) return true;
  if (ctx.JsonOut()) {
    std::printf("{\"next_page_token\":%s}\n", JsonString(next_page_token).c_str());
  } else {
    std::fprintf(stderr, "more: --page-token %s (or --all)\n", next_page_token.c_str());
  }
  return false;
}

std::vector<std::string> JobHeader(bool wide) {
  std::vector<std::string> h = {"NAME", "STATE",     "STAGE %", "INPUT",
                                "K",    "REDUCTION", "CREATED", "DURATION"};
  if (wide) {
    for (const char* c : {"ACHIEVED", "POLICY", "VIEWS", "ARTIFACTS", "MESSAGE"}) h.push_back(c);
  }
  return h;
}

std::vector<std::string> JobRow(CliContext& ctx, const v1::Job& j, bool wide) {
  const v1::Volume* vol = GetVolume(ctx, j.spec().volume());
  std::string stage = "-";
  if (j.state() == v1::RUNNING && !j.progress().stage().empty()) {
    stage = j.progress().stage() + " " + Percent(j.progress().fraction());
  }
  std::vector<std::string> r = {ShortId(j.name()),
                                v1::JobState_Name(j.state()),
                                stage,
                                vol != nullptr ? vol->display_name() : j.spec().volume(),
                                std::to_string(j.spec().regions()),
                                Percent(j.spec().target_reduction()),
                                FormatTime(j.create_time()),
                                FormatDuration(JobSeconds(j))};
  if (wide) {
    const JobSummary s = SummarizeJob(j, 0);
    r.push_back(j.state() == v1::SUCCEEDED
                    ? Percent(s.achieved_reduction, 1) + (s.reached_target ? "" : " (short)")
                    : "-");
    r.push_back(AsciiLower(v1::SimplifyPolicy_Name(j.spec().policy())));
    std::string views;
    for (const auto& v : j.spec().views()) views += (views.empty() ? "" : " ") + v;
    r.push_back(views.empty() ? "-" : views);
    r.push_back(j.artifacts_size() > 0 ? std::to_string(j.artifacts_size()) + " files, " +
                                             FormatBytes(s.artifact_bytes)
                                       : "-");
    r.push_back(j.error().message().empty() ? "-" : j.error().message().substr(0, 80));
  }
  return r;
}

void PrintJobLine(CliContext& ctx, const v1::Job& j) {
  if (ctx.JsonOut()) {
    std::printf("%s\n", ToJson(j).c_str());
    return;
  }
  PrintTable({JobHeader(false), JobRow(ctx, j, false)});
}

void PrintStudyTable(const CliContext& ctx, const std::vector<StudyRow>& rows) {
  if (ctx.JsonOut()) {
    for (const auto& r : rows) {
      std::printf("{\"job\":%s,\"input\":%s,\"state\":%s,\"detail\":%s}\n",
                  JsonString(r.job == "-" ? "" : r.job).c_str(), JsonString(r.input).c_str(),
                  JsonString(r.state).c_str(), JsonString(r.detail).c_str());
    }
    std::fflush(stdout);
    return;
  }
  std::vector<std::vector<std::string>> table = {{"JOB", "INPUT", "STATE", "DETAIL"}};
  for (const auto& r : rows) {
    table.push_back({ShortId(r.job), r.input, r.state, r.detail.empty() ? "-" : r.detail});
  }
  PrintTable(table);
  std::fflush(stdout);
}

void PrintStudyCounts(const CliContext& ctx, const std::vector<StudyRow>& rows, bool jobs) {
  if (ctx.flags.quiet) return;
  std::map<std::string, int> by_state;
  int studies = 0;
  for (const auto& r : rows) {
    ++by_state[r.state];
    if (r.state != "SKIPPED") ++studies;
  }
  std::string text =
      "decima: " + std::to_string(studies) +
      (jobs ? (studies == 1 ? " job" : " jobs") : (studies == 1 ? " study" : " studies"));
  std::string sep = ": ";
  for (const auto& [state, n] : by_state) {
    if (state == "SKIPPED") continue;
    text += sep + std::to_string(n) + " " + state;
    sep = ", ";
  }
  if (by_state.count("SKIPPED") != 0) {
    text += "; " + std::to_string(by_state["SKIPPED"]) + " skipped";
  }
  std::fprintf(stderr, "%s\n", text.c_str());
}

}  // namespace decima::client
