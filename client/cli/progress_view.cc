#include "client/cli/progress_view.h"

#include <algorithm>

#include "client/cli/output.h"
#include "client/client_lib.h"

namespace decima::client {

ProgressView::ProgressView(std::string name, std::FILE* out, bool tty, bool quiet,
                           std::function<int()> columns)
    : name_(std::move(name)), out_(out), tty_(tty), quiet_(quiet), columns_(std::move(columns)) {}

double ProgressView::Elapsed() const {
  const double s = SecondsSince(start_time_);
  return s >= 0 ? s
                : std::chrono::duration<double>(std::chrono::steady_clock::now() - watch_start_)
                      .count();
}

double ProgressView::SinceEvent() const {
  if (current_time_.seconds() == 0) return 0;
  return std::max(0.0, SecondsSince(current_time_));
}

void ProgressView::Draw() {
  if (quiet_ || current_.stage().empty()) return;
  if (tty_) {
    std::string l =
        OverallBar(current_, Elapsed(), 24, with_curve_, SinceEvent()) + "  " + current_.message();
    l.resize(std::min<size_t>(l.size(), static_cast<size_t>(columns_() - 1)));
    std::fprintf(out_, "\r\033[K%s", l.c_str());
    bar_open_ = true;
    return;
  }
  const int decile = static_cast<int>(JobFraction(current_, with_curve_) * 10);
  if (current_.stage() == plain_stage_ && decile == plain_decile_ &&
      std::chrono::steady_clock::now() - plain_at_ < std::chrono::seconds(15)) {
    return;
  }
  plain_stage_ = current_.stage();
  plain_decile_ = decile;
  plain_at_ = std::chrono::steady_clock::now();
  std::fprintf(out_, "%s %s %s\n", ShortId(name_).c_str(),
               OverallBar(current_, Elapsed(), 0, with_curve_, SinceEvent()).substr(3).c_str(),
               TerminalSafe(current_.message()).c_str());
}

void ProgressView::Say(const std::string& text) {
  if (quiet_) return;
  if (bar_open_) std::fprintf(out_, "\r\033[K");
  bar_open_ = false;
  std::fprintf(out_, "%s\n", text.c_str());
}

void ProgressView::EndStream() {
  if (bar_open_ && !quiet_) std::fprintf(out_, "\n");
  bar_open_ = false;
}

void ProgressView::OnEvent(const v1::JobEvent& ev, bool first_contact) {
  if (ev.has_snapshot()) {
    const v1::Job& j = ev.snapshot();
    with_curve_ = JobWithCurve(j);
    start_time_ = j.start_time();
    if (!first_contact) return;
    replay_until_ = j.last_sequence();
    // The first contact: one line saying where the job is, no internal numbers.
    std::string text = "decima: watching " + j.name() + ": " + v1::JobState_Name(j.state());
    if (j.state() == v1::RUNNING && !j.progress().stage().empty()) {
      text += ", " + j.progress().stage() + " " + Percent(j.progress().fraction());
    }
    if (j.start_time().seconds() != 0) {
      text += ", started " + FormatDuration(SecondsSince(j.start_time())) + " ago";
    }
    Say(text);
    if (j.state() == v1::RUNNING) current_ = j.progress(), current_time_ = {};
    return;
  }
  if (!ev.has_heartbeat() && ev.sequence() <= replay_until_) {
    // Stored events replayed after the snapshot: the snapshot line said where the job is, so
    // they only bring the bar up to date.
    if (ev.has_progress()) current_ = ev.progress(), current_time_ = ev.time();
    if (ev.has_state_change() && ev.state_change().state() == v1::RUNNING) start_time_ = ev.time();
    if (ev.sequence() == replay_until_) Draw();
    return;
  }
  if (ev.has_progress()) {
    if (start_time_.seconds() == 0) start_time_ = ev.time();
    current_ = ev.progress();
    current_time_ = ev.time();
    Draw();
  } else if (ev.has_heartbeat()) {
    if (tty_) Draw();  // the elapsed time moves while a stage is quiet
  } else if (ev.has_state_change()) {
    const auto& sc = ev.state_change();
    std::string text = ShortId(name_) + " " + v1::JobState_Name(sc.state());
    if (sc.state() == v1::RUNNING) {
      start_time_ = ev.time();
    } else if (start_time_.seconds() != 0) {
      text += " after " + FormatDuration(Between(start_time_, ev.time()));
    }
    if (!sc.error().message().empty()) text += ": " + sc.error().message();
    Say(text);
  }
}

JobLinesView::JobLinesView(std::string id, std::function<void(const std::string&)> say)
    : id_(std::move(id)), say_(std::move(say)) {}

void JobLinesView::OnEvent(const v1::JobEvent& ev, bool first_contact) {
  if (ev.has_snapshot()) {
    const v1::Job& j = ev.snapshot();
    with_curve_ = JobWithCurve(j);
    if (!first_contact) return;
    replay_until_ = j.last_sequence();
    std::string text = id_ + " " + v1::JobState_Name(j.state());
    if (j.state() == v1::RUNNING && !j.progress().stage().empty()) {
      stage_ = j.progress().stage();
      text += ", " + stage_ + " " + Percent(j.progress().fraction());
    }
    say_(text);
    return;
  }
  if (ev.has_heartbeat()) return;
  if (ev.has_progress()) {
    const v1::Progress& p = ev.progress();
    const double f = JobFraction(p, with_curve_);
    const int d = static_cast<int>(f * 10);
    // Replayed events (older than the snapshot) only bring the counters up to date.
    if ((p.stage() != stage_ || d != decile_) && ev.sequence() > replay_until_) {
      say_(id_ + " " + Percent(f) + " " + p.stage() + " " + p.message());
    }
    stage_ = p.stage();
    decile_ = d;
  } else if (ev.has_state_change() && ev.sequence() > replay_until_) {
    const auto& sc = ev.state_change();
    say_(id_ + " " + v1::JobState_Name(sc.state()) +
         (sc.error().message().empty() ? "" : ": " + sc.error().message()));
  }
}

}  // namespace decima::client
