// How a watched job's progress is shown on stderr, apart from where the events come from
// (JobEventStream). One job: one overall bar across the stages, on a terminal one line redrawn
// in place (also on heartbeats, so the clock moves), otherwise plain lines (one per stage, per
// 10 points of overall progress, or per 15 s). Several jobs: plain lines prefixed with the job
// id, one per stage, per 10 points and per state change.
#pragma once

#include <google/protobuf/timestamp.pb.h>

#include <chrono>
#include <cstdio>
#include <functional>
#include <string>

#include "decima/v1/jobs.pb.h"

namespace decima::client {

class ProgressView {
 public:
  // `tty`: draw the bar in place, `columns` wide at most; `quiet`: print nothing.
  ProgressView(std::string name, std::FILE* out, bool tty, bool quiet,
               std::function<int()> columns);

  // One event of the job's stream. `first_contact`: nothing of the job was seen before, so a
  // snapshot says where the job is (one line) and the events replayed after it up to the
  // snapshot's sequence only bring the bar up to date.
  void OnEvent(const v1::JobEvent& ev, bool first_contact);
  // A line of its own (the bar's line is cleared first).
  void Say(const std::string& text);
  // The stream ended: a bar drawn in place ends its line.
  void EndStream();

 private:
  double Elapsed() const;
  // Seconds since the server sent current_ (0 when it came from a snapshot).
  double SinceEvent() const;
  void Draw();

  std::string name_;
  std::FILE* out_;
  bool tty_, quiet_;
  std::function<int()> columns_;
  bool bar_open_ = false;
  const std::chrono::steady_clock::time_point watch_start_ = std::chrono::steady_clock::now();
  google::protobuf::Timestamp start_time_;
  v1::Progress current_;
  google::protobuf::Timestamp current_time_;
  bool with_curve_ = false;   // from the snapshot's spec: the curve stage counts in the bar
  int64_t replay_until_ = 0;  // the snapshot's last_sequence: events up to it are replayed
  std::string plain_stage_;
  int plain_decile_ = -1;
  std::chrono::steady_clock::time_point plain_at_ = std::chrono::steady_clock::now();
};

// One of several watched jobs, as lines through `say` (which keeps lines whole across
// threads): the first contact, each stage, every 10 points of overall progress, each state
// change with its error.
class JobLinesView {
 public:
  JobLinesView(std::string id, std::function<void(const std::string&)> say);
  void OnEvent(const v1::JobEvent& ev, bool first_contact);

 private:
  std::string id_;
  std::function<void(const std::string&)> say_;
  int64_t replay_until_ = 0;
  bool with_curve_ = false;
  std::string stage_;
  int decile_ = -1;
};

}  // namespace decima::client
