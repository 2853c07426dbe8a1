// Small string helpers the client's files share (the client does not link abseil).
#pragma once

#include <string>

namespace decima::client {

// ASCII lower case: flag values, file names and HTTP header names are compared this way.
inline std::string AsciiLower(std::string s) {
  for (char& c : s) {
    if (c >= 'A' && c <= 'Z') c = static_cast<char>(c - 'A' + 'a');
  }
  return s;
}

inline bool EndsWith(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() &&
         s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

}  // namespace decima::client
