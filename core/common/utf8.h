// Text that comes from outside (file headers, network peers) made safe for protobuf `string`
// fields, which must hold valid UTF-8: a Volume whose DICOM Modality held a stray Latin-1 byte
// was stored, and then every answer that carried it failed to serialize.
#pragma once

#include <string>
#include <string_view>

namespace decima {

// `s` with every byte that does not belong to a well-formed UTF-8 sequence (Unicode 15, table
// 3-7: no overlong forms, no surrogates, nothing above U+10FFFF) replaced by U+FFFD. Valid text
// comes back unchanged.
std::string ValidUtf8(std::string_view s);

}  // namespace decima
