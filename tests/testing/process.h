// Child processes and ports for tests that start real programs (PostgreSQL, storescu, ...):
// loopback only, every child waited for by its PID within a bound.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <map>
#include <string>
#include <vector>

namespace decima::testing {

// A loopback TCP port nobody listens on right now (0 if none could be had).
int FreePort();

// Starts `argv` (argv[0] a path) with stdout and stderr appended to the file `log`; the child's
// PID, or -1 if it could not be started (WaitExit then answers 127, as a shell would).
pid_t Spawn(const std::vector<std::string>& argv, const std::string& log);

// Starts `argv` with stdin from /dev/null, stdout and stderr written (truncated) to the
// files `out` and `err`, and `env` added to the inherited environment; the child's PID or -1.
pid_t Spawn(const std::vector<std::string>& argv, const std::string& out, const std::string& err,
            const std::map<std::string, std::string>& env);

// Waits up to `timeout` for `pid`: its exit code (128 + signal if a signal ended it), or -1 if
// it was still running (it is then killed with SIGKILL and reaped) or is not our child; 127 for
// the -1 of a Spawn that failed. On a timeout, `at_timeout` (if given) receives what /proc said
// of the process just before the kill (ProcessState).
int WaitExit(pid_t pid, std::chrono::seconds timeout, std::string* at_timeout = nullptr);

// One line from /proc about a live process, for a test's failure message: the program it runs
// (a child hung before exec still runs the test's binary), its state, what each thread waits in.
std::string ProcessState(pid_t pid);

}  // namespace decima::testing
