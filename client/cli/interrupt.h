// Ctrl-C while watching: the jobs go on on the server; the CLI says so, and how to come back.
#pragma once

#include <string>
#include <vector>

#include "client/cli/context.h"

namespace decima::client {

// Until DisarmInterrupt, SIGINT prints how to re-attach to `job` and cancel it, and exits 130.
void ArmInterrupt(const CliContext& ctx, const std::string& job);
// The same for several jobs: one command re-attaches to all of them.
void ArmInterruptMany(const CliContext& ctx, const std::vector<std::string>& names);
void DisarmInterrupt();

}  // namespace decima::client
