// The verbs of the `decima` CLI, one file each in client/cmd/: each adds its subcommand and
// flags (into an options struct of its own) and returns what runs it. main.cc lists them in
// the order --help shows them.
#pragma once

#include <CLI/CLI.hpp>
#include <filesystem>
#include <functional>
#include <set>
#include <string>
#include <vector>

#include "client/cli/context.h"

namespace decima::client {

struct Command {
  CLI::App* app;             // the subcommand: set when the command line chose it
  std::function<int()> run;  // the verb, after parsing; its exit code
};

Command NewCmdSubmit(CLI::App& app, CliContext& ctx);
Command NewCmdWatch(CLI::App& app, CliContext& ctx);
Command NewCmdStatus(CLI::App& app, CliContext& ctx);
Command NewCmdList(CLI::App& app, CliContext& ctx);
Command NewCmdCancel(CLI::App& app, CliContext& ctx);
Command NewCmdRetry(CLI::App& app, CliContext& ctx);
Command NewCmdFetch(CLI::App& app, CliContext& ctx);
Command NewCmdDelete(CLI::App& app, CliContext& ctx);
Command NewCmdPrune(CLI::App& app, CliContext& ctx);
Command NewCmdHealth(CLI::App& app, CliContext& ctx);
Command NewCmdVersion(CLI::App& app, CliContext& ctx);
Command NewCmdPull(CLI::App& app, CliContext& ctx);
Command NewCmdSeries(CLI::App& app, CliContext& ctx);

// fetch's download of a succeeded job's artifacts into `out` (`only`: names or kinds), also
// run by `submit --out`.
int FetchArtifacts(CliContext& ctx, const v1::Job& job, const std::filesystem::path& out,
                   const std::vector<std::string>& only);

// delete's removal of the volumes in `candidates` that no remaining job uses (each printed),
// also run by `prune --force`; adds the bytes freed to *freed.
int DeleteUnusedVolumes(CliContext& ctx, const std::set<std::string>& candidates, bool dry_run,
                        int64_t* freed);

}  // namespace decima::client
