#include "server/dicom/dicom_routes.h"

#include <google/protobuf/util/json_util.h>

#include <fstream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "server/jobs/job_spec.h"

namespace decima::server {
namespace {

bool Matches(const std::string& pattern, const std::string& value) {
  return pattern.empty() || pattern == "*" || pattern == value;
}

absl::Status Invalid(const std::string& source, const std::string& field,
                     const std::string& message) {
  return absl::InvalidArgumentError(absl::StrCat(source, ": ", field, ": ", message));
}

absl::StatusOr<std::string> OptionalString(const nlohmann::json& j, const char* key,
                                           const std::string& source, const std::string& where) {
  if (!j.contains(key)) return std::string();
  if (!j[key].is_string())
    return Invalid(source, absl::StrCat(where, ".", key), "expected a string");
  return j[key].get<std::string>();
}

}  // namespace

const DicomRoute* DicomRoutes::Match(const std::string& calling_ae,
                                     const std::string& called_ae) const {
  for (const auto& r : routes) {
    if (Matches(r.calling_ae, calling_ae) && Matches(r.called_ae, called_ae)) return &r;
  }
  return refuse_unknown_calling_ae ? nullptr : &default_route_;
}

const DicomRoute* DicomRoutes::Find(const std::string& name) const {
  for (const auto& r : routes) {
    if (r.name == name) return &r;
  }
  return name == default_route_.name ? &default_route_ : nullptr;
}

absl::StatusOr<DicomRoutes> ParseDicomRoutes(const std::string& text, const std::string& src) {
  nlohmann::json doc = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded() || !doc.is_object()) {
    return absl::InvalidArgumentError(absl::StrCat(src, ": not a JSON object"));
  }
  DicomRoutes out;
  for (const auto& [key, value] : doc.items()) {
    if (key != "routes" && key != "refuse_unknown_calling_ae") {
      return Invalid(src, key, "unknown key (expected routes, refuse_unknown_calling_ae)");
    }
  }
  if (doc.contains("refuse_unknown_calling_ae")) {
    if (!doc["refuse_unknown_calling_ae"].is_boolean()) {
      return Invalid(src, "refuse_unknown_calling_ae", "expected true or false");
    }
    out.refuse_unknown_calling_ae = doc["refuse_unknown_calling_ae"].get<bool>();
  }
  if (!doc.contains("routes") || !doc["routes"].is_array()) {
    return Invalid(src, "routes", "expected an array");
  }
  std::set<std::string> names;
  const auto& routes = doc["routes"];
  for (size_t i = 0; i < routes.size(); ++i) {
    const std::string where = absl::StrCat("routes[", i, "]");
    const auto& r = routes[i];
    if (!r.is_object()) return Invalid(src, where, "expected an object");
    for (const auto& [key, value] : r.items()) {
      if (key != "name" && key != "calling_ae" && key != "called_ae" && key != "spec" &&
          key != "destination") {
        return Invalid(src, absl::StrCat(where, ".", key), "unknown key");
      }
    }
    DicomRoute route;
    auto name = OptionalString(r, "name", src, where);
    auto calling = OptionalString(r, "calling_ae", src, where);
    auto called = OptionalString(r, "called_ae", src, where);
    for (auto* s : {&name, &calling, &called}) {
      if (!s->ok()) return s->status();
    }
    route.name = name->empty() ? absl::StrCat("route", i) : *name;
    if (!names.insert(route.name).second || route.name == "default") {
      return Invalid(src, where + ".name", absl::StrCat("'", route.name, "' is not unique"));
    }
    route.calling_ae = *calling;
    route.called_ae = *called;
    if (r.contains("spec")) {
      auto st = google::protobuf::util::JsonStringToMessage(r["spec"].dump(), &route.spec);
      if (!st.ok()) return Invalid(src, where + ".spec", std::string(st.message()));
      if (!route.spec.volume().empty()) {
        return Invalid(src, where + ".spec.volume", "set by the receiver; leave it out");
      }
      // Validated now, so a bad route fails at start-up rather than when a series arrives.
      v1::JobSpec probe = route.spec;
      probe.set_volume("volumes/route-check");
      if (auto n = NormalizeJobSpec(probe); !n.ok()) {
        return Invalid(src, where + ".spec", std::string(n.status().message()));
      }
    }
    if (r.contains("destination")) {
      const auto& d = r["destination"];
      const std::string dw = where + ".destination";
      if (!d.is_object()) return Invalid(src, dw, "expected an object");
      DicomDestination& dest = route.destination;
      for (const auto& [key, value] : d.items()) {
        if (key == "timeout_seconds") {
          if (!value.is_number_integer() || value.get<int>() < 1 || value.get<int>() > 3600) {
            return Invalid(src, dw + ".timeout_seconds", "expected an integer 1..3600");
          }
          dest.timeout_seconds = value.get<int>();
          continue;
        }
        if (!value.is_string()) return Invalid(src, dw + "." + key, "expected a string");
        const std::string v = value.get<std::string>();
        if (key == "stow_url") {
          dest.stow_url = v;
        } else if (key == "dicom") {
          const size_t colon = v.rfind(':');
          int port = 0;
          if (colon == std::string::npos || colon == 0 ||
              !absl::SimpleAtoi(v.substr(colon + 1), &port) || port < 1 || port > 65535) {
            return Invalid(src, dw + ".dicom", absl::StrCat("'", v, "', expected host:port"));
          }
          dest.host = v.substr(0, colon);
          dest.port = port;
        } else if (key == "aet") {
          dest.aet = v;
        } else if (key == "username") {
          dest.username = v;
        } else if (key == "password") {
          dest.password = v;
        } else if (key == "bearer_token") {
          dest.bearer_token = v;
        } else if (key == "ca_file") {
          dest.ca_file = v;
        } else {
          return Invalid(src, dw + "." + key, "unknown key");
        }
      }
      if (dest.stow_url.empty() == dest.host.empty()) {
        return Invalid(src, dw, "set exactly one of stow_url and dicom");
      }
      if (!dest.host.empty() && (dest.aet.empty() || dest.aet.size() > 16)) {
        return Invalid(src, dw + ".aet", "the peer's AE title (1..16 characters) is needed");
      }
    }
    out.routes.push_back(std::move(route));
  }
  return out;
}

absl::StatusOr<DicomRoutes> LoadDicomRoutes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("--dicom-routes ", path, ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  return ParseDicomRoutes(ss.str(), path);
}

}  // namespace decima::server
