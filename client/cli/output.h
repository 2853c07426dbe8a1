// How the `decima` CLI prints: JSON lines, tables with columns as wide as their widest cell,
// times, percentages, the job table's rows, and the table of several studies or jobs. Every
// text the server sent goes through TerminalSafe in a table.
#pragma once

#include <google/protobuf/message.h>
#include <google/protobuf/timestamp.pb.h>

#include <string>
#include <vector>

#include "client/cli/context.h"

namespace decima::client {

// The message as one line of JSON, with the proto's field names.
std::string ToJson(const google::protobuf::Message& m);
// `s` as a quoted JSON string.
std::string JsonString(const std::string& s);
// "jobs/abc" -> "abc".
std::string ShortId(const std::string& name);
// Local "2026-01-02 03:04:05"; "-" when unset.
std::string FormatTime(const google::protobuf::Timestamp& t);
std::string Percent(double f, int decimals = 0);
// Seconds from `t` to now; -1 when unset.
double SecondsSince(const google::protobuf::Timestamp& t);
// Seconds from `a` to `b`; -1 when either is unset.
double Between(const google::protobuf::Timestamp& a, const google::protobuf::Timestamp& b);
// How long the job ran (or has been running); -1 before it started.
double JobSeconds(const v1::Job& j);
// stderr's width on a terminal, else 100.
int TerminalColumns();

// A table printed with columns as wide as their widest cell (kubectl's plain output).
void PrintTable(const std::vector<std::vector<std::string>>& rows);

// After one page of a listing: true to fetch the next page (--all); else, when there is one,
// says how to get it (a JSON line, or a hint on stderr) and returns false.
bool ContinueListing(const CliContext& ctx, const std::string& next_page_token, bool all);

// The columns of `decima list` (-o wide adds five).
std::vector<std::string> JobHeader(bool wide);
std::vector<std::string> JobRow(CliContext& ctx, const v1::Job& j, bool wide);
// One job as a JSON line, or as a table of one row.
void PrintJobLine(CliContext& ctx, const v1::Job& j);

// One row of the table of several studies or jobs.
struct StudyRow {
  std::string job = "-";  // "jobs/..." once made
  std::string input;
  std::string state;  // a JobState name, or REFUSED (no job was made) or SKIPPED (no volume)
  std::string detail;
  int rc = kOk;  // this study's part of the exit code (BatchExitCode); SKIPPED rows have none
};
// The table of a batch (stdout): JOB, INPUT, STATE, DETAIL; with --json one object per row.
void PrintStudyTable(const CliContext& ctx, const std::vector<StudyRow>& rows);
// "10 studies: 9 SUCCEEDED, 1 FAILED; 1 skipped" on stderr (`jobs`: "10 jobs: ...").
void PrintStudyCounts(const CliContext& ctx, const std::vector<StudyRow>& rows, bool jobs = false);

}  // namespace decima::client
