// decima-server: the gRPC service. Flags (each also an environment variable):
//   --listen ADDR         DECIMA_LISTEN          default 127.0.0.1:50051
//   --data-dir DIR        DECIMA_DATA_DIR        default $XDG_DATA_HOME/decima or ./decima-data
//   --store S             DECIMA_STORE           sqlite (default) or postgresql://...
//   --store-file F        DECIMA_STORE_FILE      the --store value read from a file (a Secret)
//   --workers N           DECIMA_WORKERS         default 1
//   --max-queued N        DECIMA_MAX_QUEUED      default 1000
//   --max-upload-mb N     DECIMA_MAX_UPLOAD_MB   default 2048
//   --token-file F        DECIMA_TOKEN_FILE      one bearer token, its holder is admin
//   --tokens-file F       DECIMA_TOKENS_FILE     principals and roles (call_guard.h)
//   --tls-cert F --tls-key F  DECIMA_TLS_CERT / DECIMA_TLS_KEY
//   --tls-client-ca F     DECIMA_TLS_CLIENT_CA   require client certificates signed by F
//   --audit-log F         DECIMA_AUDIT_LOG       default <data-dir>/audit-<hostname>.log
// `decima-server --run-job REQUEST` is the job child process (worker_process.h).
#include <string>

#include "server/app/server.h"
#include "server/app/server_options.h"
#include "server/dicom/dicom_sender.h"
#include "server/jobs/worker_process.h"
#include "spdlog/spdlog.h"

using namespace decima::server;

int main(int argc, char** argv) {
  if (argc == 3 && std::string(argv[1]) == "--run-job") return RunJobProcess(argv[2], kWorkerFd);
  EnableDcmtkTcpNoDelay();  // before any thread: setenv is not thread-safe

  ServerOptions options;
  if (std::optional<int> exit_code = ParseFlags(argc, argv, &options)) return *exit_code;
  auto server = Server::Start(options);
  if (!server.ok()) {
    spdlog::error("{}", std::string(server.status().message()));
    return 1;  // the exit codes are listed in --help (server_flags.cc)
  }
  (*server)->Drain((*server)->WaitForStopSignal());
  return 0;
}
