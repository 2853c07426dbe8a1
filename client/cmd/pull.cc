// decima pull --dicomweb URL --study UID [--series UID] --out DIR: download only (WADO-RS).
#include "client/cli/dicomweb_flags.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct PullOptions {
  DicomWebFlags dicomweb;
  std::filesystem::path out;
};

int RunPull(CliContext& ctx, PullOptions& o) {
  if (int rc = ReadDicomWebToken(o.dicomweb); rc != kOk) return rc;
  return PullDicomWebInto(ctx, o.dicomweb, o.out, ctx.JsonOut(), {});
}

}  // namespace

Command NewCmdPull(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<PullOptions>();
  auto* cmd = app.add_subcommand("pull", "download a DICOM series or study by WADO-RS");
  AddDicomWebFlags(cmd, o->dicomweb, /*is_pull=*/true);
  cmd->add_option("--out", o->out, "destination folder")->required();
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunPull(ctx, *o); }};
}

}  // namespace decima::client
