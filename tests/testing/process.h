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

// fork + exec `argv` (argv[0] a path) with stdout and stderr appended to the file `log`; the
// child's PID.
pid_t Spawn(const std::vector<std::string>& argv, const std::string& log);

// fork + exec `argv` with stdin from /dev/null, stdout and stderr written (truncated) to the
// files `out` and `err`, and `env` added to the inherited environment; the child's PID.
pid_t Spawn(const std::vector<std::string>& argv, const std::string& out, const std::string& err,
            const std::map<std::string, std::string>& env);

// Waits up to `timeout` for `pid`: its exit code (128 + signal if a signal ended it), or -1 if
// it was still running (it is then killed with SIGKILL and reaped) or is not our child.
int WaitExit(pid_t pid, std::chrono::seconds timeout);

}  // namespace decima::testing
