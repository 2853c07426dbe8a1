// grpc.reflection.v1alpha.ServerReflection behind the caller check: the descriptors of the
// served API come from the linked generated code, so tools (grpcurl, grpc_cli) can call the
// server without .proto files, but only a caller who may call decima.v1 may ask (issue 16:
// reflection tells an anonymous caller every method and field of the API).
#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>

#include <set>

#include "absl/strings/str_cat.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "server/api/service.h"

namespace decima::server {
namespace {

namespace rv = ::grpc::reflection::v1alpha;
using google::protobuf::Descriptor;
using google::protobuf::DescriptorPool;
using google::protobuf::FieldDescriptor;
using google::protobuf::FileDescriptor;

class ReflectionService final : public rv::ServerReflection::Service {
 public:
  ReflectionService(const CallGuard* guard, std::vector<std::string> services)
      : guard_(guard), services_(std::move(services)) {}

  grpc::Status ServerReflectionInfo(
      grpc::ServerContext* ctx,
      grpc::ServerReaderWriter<rv::ServerReflectionResponse, rv::ServerReflectionRequest>* stream)
      override {
    Principal caller;
    if (grpc::Status st = guard_->Check(ctx, &caller); !st.ok()) return st;
    rv::ServerReflectionRequest request;
    // One answer per request until the client half-closes; a failed write means it is gone.
    while (stream->Read(&request)) {
      if (!stream->Write(Answer(request))) break;
    }
    return grpc::Status::OK;
  }

 private:
  rv::ServerReflectionResponse Answer(const rv::ServerReflectionRequest& request) const {
    rv::ServerReflectionResponse response;
    response.set_valid_host(request.host());
    *response.mutable_original_request() = request;
    const DescriptorPool* pool = DescriptorPool::generated_pool();
    auto not_found = [&response](const std::string& what) {
      auto* e = response.mutable_error_response();
      e->set_error_code(grpc::StatusCode::NOT_FOUND);
      e->set_error_message(what);
      return response;
    };
    switch (request.message_request_case()) {
      case rv::ServerReflectionRequest::kListServices:
        for (const std::string& name : services_) {
          response.mutable_list_services_response()->add_service()->set_name(name);
        }
        return response;
      case rv::ServerReflectionRequest::kFileByFilename: {
        const FileDescriptor* file = pool->FindFileByName(request.file_by_filename());
        if (!file) return not_found(absl::StrCat("no file '", request.file_by_filename(), "'"));
        AddFileAndDependencies(file, response.mutable_file_descriptor_response());
        return response;
      }
      case rv::ServerReflectionRequest::kFileContainingSymbol: {
        const FileDescriptor* file =
            pool->FindFileContainingSymbol(request.file_containing_symbol());
        if (!file) {
          return not_found(absl::StrCat("no symbol '", request.file_containing_symbol(), "'"));
        }
        AddFileAndDependencies(file, response.mutable_file_descriptor_response());
        return response;
      }
      case rv::ServerReflectionRequest::kFileContainingExtension: {
        const auto& ext = request.file_containing_extension();
        const Descriptor* type = pool->FindMessageTypeByName(ext.containing_type());
        const FieldDescriptor* field =
            type ? pool->FindExtensionByNumber(type, ext.extension_number()) : nullptr;
        if (!field) {
          return not_found(absl::StrCat("no extension ", ext.extension_number(), " of '",
                                        ext.containing_type(), "'"));
        }
        AddFileAndDependencies(field->file(), response.mutable_file_descriptor_response());
        return response;
      }
      case rv::ServerReflectionRequest::kAllExtensionNumbersOfType: {
        const Descriptor* type =
            pool->FindMessageTypeByName(request.all_extension_numbers_of_type());
        if (!type) {
          return not_found(
              absl::StrCat("no message type '", request.all_extension_numbers_of_type(), "'"));
        }
        std::vector<const FieldDescriptor*> extensions;
        pool->FindAllExtensions(type, &extensions);
        auto* numbers = response.mutable_all_extension_numbers_response();
        numbers->set_base_type_name(type->full_name());
        for (const FieldDescriptor* f : extensions) numbers->add_extension_number(f->number());
        return response;
      }
      case rv::ServerReflectionRequest::MESSAGE_REQUEST_NOT_SET:
        break;
    }
    auto* e = response.mutable_error_response();
    e->set_error_code(grpc::StatusCode::INVALID_ARGUMENT);
    e->set_error_message(
        "message_request: expected one of file_by_filename, "
        "file_containing_symbol, file_containing_extension, "
        "all_extension_numbers_of_type, list_services");
    return response;
  }

  // The file first, then every file it imports, transitively, each once: a client builds its
  // pool from one answer.
  static void AddFileAndDependencies(const FileDescriptor* file, rv::FileDescriptorResponse* out) {
    std::set<const FileDescriptor*> seen{file};
    std::vector<const FileDescriptor*> todo{file};
    for (size_t i = 0; i < todo.size(); ++i) {
      google::protobuf::FileDescriptorProto proto;
      todo[i]->CopyTo(&proto);
      out->add_file_descriptor_proto(proto.SerializeAsString());
      for (int d = 0; d < todo[i]->dependency_count(); ++d) {
        if (seen.insert(todo[i]->dependency(d)).second) todo.push_back(todo[i]->dependency(d));
      }
    }
  }

  const CallGuard* guard_;
  const std::vector<std::string> services_;
};

}  // namespace

std::unique_ptr<grpc::Service> MakeReflectionService(const CallGuard* guard,
                                                     std::vector<std::string> service_names) {
  return std::make_unique<ReflectionService>(guard, std::move(service_names));
}

}  // namespace decima::server
