// Structural check of a DICOM Part 10 file before GDCM parses it (internal to core/io).
//
// Debian's GDCM is built with assertions enabled and aborts the process on some malformed input
// (e.g. a file truncated inside an element header), and it allocates whatever an element's
// length field claims before reading it. CheckDicomStructure walks the file's element tree
// without interpreting values and accepts it only if every element header is complete, every
// defined length fits in the bytes that remain, every undefined-length sequence, item and
// encapsulated pixel data is properly delimited, and nesting stays shallow. A file that passes
// is safe to hand to gdcm::Reader as far as element structure goes.
#pragma once

#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace decima::dicom_internal {

// Maximum nesting of sequences accepted; real data sets nest a handful of levels.
inline constexpr int kMaxSequenceDepth = 16;

// Checks `bytes` (a whole file: 128-byte preamble, "DICM", group 0002 in explicit VR little
// endian, then the data set in the transfer syntax named by (0002,0010)). Implicit VR little
// endian, explicit VR little and big endian, and all encapsulated (compressed) syntaxes are
// walked; deflated syntaxes are refused. On failure returns InvalidArgument whose message
// (without file name) names the byte offset and the element at fault.
absl::Status CheckDicomStructure(absl::string_view bytes);

}  // namespace decima::dicom_internal
