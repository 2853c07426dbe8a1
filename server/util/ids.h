// Resource ids: the names of jobs, volumes, uploads and spooled files.
#pragma once

#include <string>

namespace decima::server {

// A random resource id: 16 lower-case hex characters.
std::string NewId();

}  // namespace decima::server
