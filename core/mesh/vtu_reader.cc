// ReadVtu: the VTK XML UnstructuredGrid subset described in mesh_io.h.
//
// The file is outside data, so nothing is trusted: a small hand-written XML parser reads the
// header (the only XML we need; names and values are taken verbatim, without entity decoding),
// and every array length is checked against the piece's counts and against the bytes actually
// left in the file BEFORE anything is allocated. For zlib data the bound is deflate's maximum
// ratio (1032:1), for LZMA (.xz) data a bound of 16384:1 (1 MiB of zeros, the best case of a
// block, is 284 bytes: 3,692:1), so a tiny file cannot make us allocate gigabytes.
#include <fcntl.h>
#include <lzma.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "core/common/status.h"
#include "core/mesh/mesh_io.h"

namespace decima {
namespace {

static_assert(std::endian::native == std::endian::little, "the .vtu reader assumes little endian");

constexpr uint64_t kMaxDeflateRatio = 1032;  // deflate's best case: 258 bytes per 2 bits
constexpr uint64_t kMaxLzmaRatio = 16384;    // see the top of the file
// The .xz decoder's memory limit: LZMA2 at preset 9 needs 65 MiB to decode (a 64 MiB dictionary).
constexpr uint64_t kLzmaMemLimit = uint64_t{128} << 20;
constexpr size_t kMaxXmlElements = 10000;  // a .vtu header has a few dozen
constexpr size_t kMaxXmlDepth = 32;
constexpr uint64_t kMaxCount = std::numeric_limits<int32_t>::max();  // points and cells

// ---------------------------------------------------------------------------------------------
// Minimal XML

struct XmlElement {
  absl::string_view name;
  std::vector<std::pair<absl::string_view, absl::string_view>> attrs;
  absl::string_view text;  // character data before the first child element
  std::vector<int> children;

  std::optional<absl::string_view> Attr(absl::string_view key) const {
    for (const auto& [k, v] : attrs)
      if (k == key) return v;
    return std::nullopt;
  }
};

bool IsSpace(char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r'; }
bool IsNameChar(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
         c == ':' || c == '-' || c == '.';
}

class XmlDocument {
 public:
  // Parses `text`. If `stop_tag` is met as a start tag, parsing ends right after it (its end is
  // returned in stop_end) and still-open elements are accepted as closed.
  absl::Status Parse(absl::string_view text, absl::string_view stop_tag) {
    size_t pos = 0;
    std::vector<int> stack;
    auto error = [&](absl::string_view what) {
      return absl::InvalidArgumentError(absl::StrCat("malformed XML at byte ", pos, ": ", what));
    };
    const size_t n = text.size();
    while (true) {
      const size_t lt = text.find('<', pos);
      const size_t text_end = lt == absl::string_view::npos ? n : lt;
      if (stack.empty()) {
        for (size_t i = pos; i < text_end; ++i)
          if (!IsSpace(text[i])) return error("text outside the root element");
      } else if (elements_[stack.back()].children.empty()) {
        XmlElement& e = elements_[stack.back()];
        e.text = text.substr(e.text.data() - text.data(), text_end - (e.text.data() - text.data()));
      }
      if (lt == absl::string_view::npos) break;
      pos = lt;
      absl::string_view rest = text.substr(pos);
      if (absl::StartsWith(rest, "<?") || absl::StartsWith(rest, "<!--")) {
        const absl::string_view close = rest[1] == '?' ? "?>" : "-->";
        const size_t end = rest.find(close);
        if (end == absl::string_view::npos) return error("unterminated declaration or comment");
        pos += end + close.size();
        continue;
      }
      if (absl::StartsWith(rest, "<!")) return error("DOCTYPE/CDATA sections are not supported");
      if (absl::StartsWith(rest, "</")) {
        size_t i = pos + 2, b = i;
        while (i < n && IsNameChar(text[i])) ++i;
        const absl::string_view name = text.substr(b, i - b);
        while (i < n && IsSpace(text[i])) ++i;
        if (i >= n || text[i] != '>') return error("unterminated end tag");
        if (stack.empty() || elements_[stack.back()].name != name)
          return error(absl::StrCat("unexpected end tag </", name, ">"));
        stack.pop_back();
        pos = i + 1;
        continue;
      }
      // Start tag.
      size_t i = pos + 1, b = i;
      while (i < n && IsNameChar(text[i])) ++i;
      if (i == b) return error("expected an element name after '<'");
      if (elements_.size() >= kMaxXmlElements) return error("too many XML elements");
      if (stack.size() >= kMaxXmlDepth) return error("XML nested too deeply");
      XmlElement e;
      e.name = text.substr(b, i - b);
      bool self_closing = false;
      while (true) {
        while (i < n && IsSpace(text[i])) ++i;
        if (i >= n) return error(absl::StrCat("unterminated start tag <", e.name, ">"));
        if (text[i] == '>') {
          ++i;
          break;
        }
        if (text[i] == '/') {
          if (i + 1 >= n || text[i + 1] != '>') return error("expected '/>'");
          self_closing = true;
          i += 2;
          break;
        }
        const size_t kb = i;
        while (i < n && IsNameChar(text[i])) ++i;
        if (i == kb) return error(absl::StrCat("bad attribute in <", e.name, ">"));
        const absl::string_view key = text.substr(kb, i - kb);
        while (i < n && IsSpace(text[i])) ++i;
        if (i >= n || text[i] != '=') return error(absl::StrCat("attribute ", key, " has no '='"));
        ++i;
        while (i < n && IsSpace(text[i])) ++i;
        if (i >= n || (text[i] != '"' && text[i] != '\''))
          return error(absl::StrCat("attribute ", key, " is not quoted"));
        const char quote = text[i++];
        const size_t vb = i;
        while (i < n && text[i] != quote && text[i] != '<') ++i;
        if (i >= n || text[i] != quote)
          return error(absl::StrCat("unterminated value of attribute ", key));
        if (e.Attr(key)) return error(absl::StrCat("duplicate attribute ", key));
        e.attrs.emplace_back(key, text.substr(vb, i - vb));
        ++i;
      }
      e.text = text.substr(i, 0);
      const int id = static_cast<int>(elements_.size());
      if (stack.empty()) {
        if (!elements_.empty()) return error("more than one root element");
      } else {
        elements_[stack.back()].children.push_back(id);
      }
      elements_.push_back(std::move(e));
      pos = i;
      if (!stop_tag.empty() && elements_.back().name == stop_tag) {
        stop_end = pos;
        stopped = true;
        return absl::OkStatus();
      }
      if (!self_closing) stack.push_back(id);
    }
    if (!stack.empty())
      return error(absl::StrCat("end of file inside <", elements_[stack.back()].name, ">"));
    if (elements_.empty()) return error("no root element");
    return absl::OkStatus();
  }

  const XmlElement& root() const { return elements_[0]; }
  const XmlElement& at(int id) const { return elements_[id]; }
  // Children of `e` named `name`.
  std::vector<const XmlElement*> Children(const XmlElement& e, absl::string_view name) const {
    std::vector<const XmlElement*> out;
    for (int c : e.children)
      if (elements_[c].name == name) out.push_back(&elements_[c]);
    return out;
  }

  bool stopped = false;
  size_t stop_end = 0;

 private:
  std::vector<XmlElement> elements_;
};

std::optional<uint64_t> ParseUint(absl::string_view s) {
  while (!s.empty() && IsSpace(s.front())) s.remove_prefix(1);
  while (!s.empty() && IsSpace(s.back())) s.remove_suffix(1);
  uint64_t v = 0;
  auto r = std::from_chars(s.data(), s.data() + s.size(), v);
  if (s.empty() || r.ec != std::errc() || r.ptr != s.data() + s.size()) return std::nullopt;
  return v;
}

// ---------------------------------------------------------------------------------------------
// Data types

enum class VtkType {
  kInt8,
  kUInt8,
  kInt16,
  kUInt16,
  kInt32,
  kUInt32,
  kInt64,
  kUInt64,
  kFloat32,
  kFloat64
};

std::optional<VtkType> ParseVtkType(absl::string_view s) {
  static constexpr std::pair<absl::string_view, VtkType> kNames[] = {
      {"Int8", VtkType::kInt8},       {"UInt8", VtkType::kUInt8},   {"Int16", VtkType::kInt16},
      {"UInt16", VtkType::kUInt16},   {"Int32", VtkType::kInt32},   {"UInt32", VtkType::kUInt32},
      {"Int64", VtkType::kInt64},     {"UInt64", VtkType::kUInt64}, {"Float32", VtkType::kFloat32},
      {"Float64", VtkType::kFloat64}, {"Char", VtkType::kInt8},     {"UChar", VtkType::kUInt8}};
  for (const auto& [name, t] : kNames)
    if (name == s) return t;
  return std::nullopt;
}

size_t TypeSize(VtkType t) {
  switch (t) {
    case VtkType::kInt8:
    case VtkType::kUInt8:
      return 1;
    case VtkType::kInt16:
    case VtkType::kUInt16:
      return 2;
    case VtkType::kInt32:
    case VtkType::kUInt32:
    case VtkType::kFloat32:
      return 4;
    default:
      return 8;
  }
}

template <typename T>
constexpr VtkType TypeOf() {
  if constexpr (std::is_same_v<T, float>) return VtkType::kFloat32;
  if constexpr (std::is_same_v<T, double>) return VtkType::kFloat64;
  if constexpr (std::is_same_v<T, uint8_t>) return VtkType::kUInt8;
  if constexpr (std::is_same_v<T, int32_t>) return VtkType::kInt32;
  if constexpr (std::is_same_v<T, int64_t>) return VtkType::kInt64;
}

// Calls f(S{}) with S the C type of `t`.
template <typename F>
auto Dispatch(VtkType t, F&& f) {
  switch (t) {
    case VtkType::kInt8:
      return f(int8_t{});
    case VtkType::kUInt8:
      return f(uint8_t{});
    case VtkType::kInt16:
      return f(int16_t{});
    case VtkType::kUInt16:
      return f(uint16_t{});
    case VtkType::kInt32:
      return f(int32_t{});
    case VtkType::kUInt32:
      return f(uint32_t{});
    case VtkType::kInt64:
      return f(int64_t{});
    case VtkType::kUInt64:
      return f(uint64_t{});
    case VtkType::kFloat32:
      return f(float{});
    default:
      return f(double{});
  }
}

// ---------------------------------------------------------------------------------------------
// Byte sources: raw bytes at a file offset, or base64 text (inline or appended).

class ByteSource {
 public:
  virtual ~ByteSource() = default;
  // Reads exactly n bytes or fails (truncated / invalid encoding).
  virtual absl::Status Read(uint8_t* dst, uint64_t n) = 0;
  // No more than this many bytes can still be read.
  virtual uint64_t Remaining() const = 0;
};

class FileSource : public ByteSource {
 public:
  FileSource(int fd, uint64_t pos, uint64_t end) : fd_(fd), pos_(pos), end_(end) {}
  absl::Status Read(uint8_t* dst, uint64_t n) override {
    if (n > Remaining())
      return absl::InvalidArgumentError(absl::StrCat("truncated: needs ", n, " bytes at offset ",
                                                     pos_, ", the file ends at ", end_));
    while (n > 0) {
      const ssize_t r = ::pread(fd_, dst, std::min<uint64_t>(n, uint64_t{1} << 30), pos_);
      if (r <= 0) {
        return absl::DataLossError(absl::StrCat("read failed at offset ", pos_, ": ",
                                                r == 0 ? "unexpected end" : std::strerror(errno)));
      }
      dst += r;
      pos_ += r;
      n -= r;
    }
    return absl::OkStatus();
  }
  uint64_t Remaining() const override { return end_ - std::min(pos_, end_); }

 private:
  int fd_;
  uint64_t pos_, end_;
};

int Base64Value(char c) {
  if (c >= 'A' && c <= 'Z') return c - 'A';
  if (c >= 'a' && c <= 'z') return c - 'a' + 26;
  if (c >= '0' && c <= '9') return c - '0' + 52;
  if (c == '+') return 62;
  if (c == '/') return 63;
  return -1;
}

// Decodes quad by quad, so streams that were encoded in several pieces (VTK encodes a compressed
// array's header apart from its blocks, hence '=' padding mid-stream) decode as one byte stream.
class Base64Source : public ByteSource {
 public:
  Base64Source(const char* begin, const char* end) : p_(begin), end_(end) {}
  absl::Status Read(uint8_t* dst, uint64_t n) override {
    while (n > 0) {
      if (npending_ > 0) {
        const int take = static_cast<int>(std::min<uint64_t>(n, npending_));
        std::memcpy(dst, pending_ + (3 - npending_), take);
        npending_ -= take;
        dst += take;
        n -= take;
        continue;
      }
      int v[4];
      int got = 0, pad = 0;
      while (got < 4) {
        if (p_ >= end_) return absl::InvalidArgumentError("truncated base64 data");
        const char c = *p_++;
        if (IsSpace(c)) continue;
        if (c == '=') {
          if (got < 2) return absl::InvalidArgumentError("misplaced '=' in base64 data");
          ++pad;
          v[got++] = 0;
          continue;
        }
        const int x = Base64Value(c);
        if (x < 0 || pad > 0)
          return absl::InvalidArgumentError(
              absl::StrCat("invalid character '", std::string(1, c), "' in base64 data"));
        v[got++] = x;
      }
      const uint32_t bits = (v[0] << 18) | (v[1] << 12) | (v[2] << 6) | v[3];
      pending_[0] = uint8_t(bits >> 16);
      pending_[1] = uint8_t(bits >> 8);
      pending_[2] = uint8_t(bits);
      // A padded quad carries 3 - pad bytes; keep them right-aligned in pending_.
      if (pad > 0) std::memmove(pending_ + pad, pending_, 3 - pad);
      npending_ = 3 - pad;
    }
    return absl::OkStatus();
  }
  uint64_t Remaining() const override { return uint64_t(end_ - p_) / 4 * 3 + 3 + npending_; }

 private:
  const char* p_;
  const char* end_;
  uint8_t pending_[3];
  int npending_ = 0;
};

// ---------------------------------------------------------------------------------------------
// The reader

struct ArraySpec {
  const XmlElement* element;
  std::string name;
  VtkType type;
  int components;
  enum Format { kAscii, kBinary, kAppended } format;
  uint64_t offset = 0;
};

class VtuReader {
 public:
  VtuReader(const std::filesystem::path& path, const VtuReadOptions& options)
      : path_(path), options_(options) {}
  ~VtuReader() {
    if (fd_ >= 0) ::close(fd_);
  }

  absl::StatusOr<TetMesh> Read();

  VtuReadReport report;  // filled by a successful Read()

 private:
  absl::Status Error(absl::string_view msg) const {
    return absl::InvalidArgumentError(absl::StrCat(path_.string(), ": ", msg));
  }
  absl::Status Unimplemented(absl::string_view msg) const {
    return absl::UnimplementedError(absl::StrCat(path_.string(), ": ", msg));
  }
  absl::Status Annotate(const absl::Status& s, absl::string_view what) const {
    return absl::Status(s.code(), absl::StrCat(path_.string(), ": ", what, ": ", s.message()));
  }

  absl::Status OpenAndReadHeader();
  absl::Status ParseHeader();
  absl::StatusOr<ArraySpec> Spec(const XmlElement& e, absl::string_view where) const;
  absl::StatusOr<const XmlElement*> FindArray(const XmlElement* section, absl::string_view name,
                                              absl::string_view section_name) const;
  // The point array holding the field (the order is documented at ReadVtu in mesh_io.h).
  absl::StatusOr<const XmlElement*> FieldArray(const XmlElement* point_data) const;

  // Reads the array's values (count tuples of `components`, count in [min_count, max_count]) into
  // `out` converted to T. Returns the number of tuples.
  template <typename T>
  absl::StatusOr<uint64_t> Load(const ArraySpec& spec, int components, uint64_t min_count,
                                uint64_t max_count, std::vector<T>* out);
  // Reads the array's bytes in its own type into a buffer obtained from alloc(bytes) after the
  // size was checked. Returns the byte count.
  absl::StatusOr<uint64_t> LoadBytes(const ArraySpec& spec, uint64_t min_bytes, uint64_t max_bytes,
                                     uint64_t value_bytes,
                                     const std::function<uint8_t*(uint64_t)>& alloc);
  absl::StatusOr<uint64_t> LoadBinary(ByteSource& src, uint64_t min_bytes, uint64_t max_bytes,
                                      uint64_t value_bytes,
                                      const std::function<uint8_t*(uint64_t)>& alloc);
  absl::StatusOr<uint64_t> LoadAscii(const ArraySpec& spec, uint64_t min_bytes, uint64_t max_bytes,
                                     const std::function<uint8_t*(uint64_t)>& alloc);

  std::filesystem::path path_;
  VtuReadOptions options_;
  int fd_ = -1;
  uint64_t file_size_ = 0;
  std::string head_;  // the XML (the whole file when nothing is appended)
  XmlDocument xml_;
  bool appended_ = false;
  bool appended_base64_ = false;
  uint64_t appended_start_ = 0;  // file offset of the byte after '_'
  std::string appended_text_;    // the appended section when base64-encoded
  int header_bytes_ = 4;         // UInt32 or UInt64 size headers
  bool compressed_ = false;
  bool lzma_ = false;  // vtkLZMADataCompressor (else zlib)
  const XmlElement* piece_ = nullptr;
  uint64_t num_points_ = 0, num_cells_ = 0;
};

absl::Status VtuReader::OpenAndReadHeader() {
  fd_ = ::open(path_.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd_ < 0) {
    const int err = errno;
    return absl::Status(absl::ErrnoToStatusCode(err),
                        absl::StrCat(path_.string(), ": cannot open: ", std::strerror(err)));
  }
  struct stat st;
  if (::fstat(fd_, &st) != 0 || !S_ISREG(st.st_mode)) return Error("not a regular file");
  file_size_ = static_cast<uint64_t>(st.st_size);

  // Read until the start of the appended data (or the whole file, whose XML then holds the data).
  const std::string kTag = "<AppendedData";
  constexpr size_t kChunk = size_t{1} << 20;
  size_t found = std::string::npos;
  while (head_.size() < file_size_) {
    const size_t old = head_.size();
    const size_t want = std::min<uint64_t>(kChunk, file_size_ - old);
    head_.resize(old + want);
    const ssize_t r = ::pread(fd_, head_.data() + old, want, old);
    if (r <= 0) return Error(absl::StrCat("read failed at offset ", old));
    head_.resize(old + r);
    found = head_.find(kTag, old >= kTag.size() ? old - kTag.size() : 0);
    if (found != std::string::npos) {
      // Make sure the tag's end and the '_' marker are in memory too.
      const size_t have = head_.size();
      const size_t extra = std::min<uint64_t>(4096, file_size_ - have);
      head_.resize(have + extra);
      const ssize_t r2 = extra ? ::pread(fd_, head_.data() + have, extra, have) : 0;
      if (r2 < 0) return Error("read failed");
      head_.resize(have + r2);
      break;
    }
  }
  if (head_.size() >= 2 && (uint8_t(head_[0]) == 0x1f && uint8_t(head_[1]) == 0x8b))
    return Error("gzip-compressed file; decompress it first");
  DECIMA_RETURN_IF_ERROR([&]() -> absl::Status {
    absl::Status s = xml_.Parse(head_, "AppendedData");
    return s.ok() ? s : Error(s.message());
  }());
  if (xml_.stopped) {
    appended_ = true;
    size_t i = xml_.stop_end;
    while (i < head_.size() && IsSpace(head_[i])) ++i;
    if (i >= head_.size() || head_[i] != '_')
      return Error("<AppendedData> must be followed by the '_' marker");
    appended_start_ = i + 1;
  }
  return absl::OkStatus();
}

absl::Status VtuReader::ParseHeader() {
  const XmlElement& root = xml_.root();
  if (root.name != "VTKFile")
    return Error(absl::StrCat("root element is <", root.name, ">, expected <VTKFile>"));
  const auto type = root.Attr("type");
  if (type != "UnstructuredGrid")
    return Error(absl::StrCat("VTKFile type is '", type.value_or("(missing)"),
                              "', expected 'UnstructuredGrid'"));
  const auto order = root.Attr("byte_order").value_or("LittleEndian");
  if (order == "BigEndian") return Unimplemented("big-endian files are not supported");
  if (order != "LittleEndian")
    return Error(absl::StrCat("byte_order '", order, "' is not LittleEndian or BigEndian"));
  const auto header_type = root.Attr("header_type").value_or("UInt32");
  if (header_type == "UInt64") {
    header_bytes_ = 8;
  } else if (header_type == "UInt32") {
    header_bytes_ = 4;
  } else {
    return Error(absl::StrCat("header_type '", header_type, "' is not UInt32 or UInt64"));
  }
  if (const auto c = root.Attr("compressor")) {
    if (*c != "vtkZLibDataCompressor" && *c != "vtkLZMADataCompressor")
      return Unimplemented(absl::StrCat("compressor '", *c,
                                        "' is not supported (only vtkZLibDataCompressor and "
                                        "vtkLZMADataCompressor)"));
    compressed_ = true;
    lzma_ = *c == "vtkLZMADataCompressor";
  }
  const auto grids = xml_.Children(root, "UnstructuredGrid");
  if (grids.size() != 1)
    return Error(absl::StrCat("expected one <UnstructuredGrid>, found ", grids.size()));
  const auto pieces = xml_.Children(*grids[0], "Piece");
  if (pieces.empty()) return Error("<UnstructuredGrid> has no <Piece>");
  if (pieces.size() > 1)
    return Unimplemented(absl::StrCat(pieces.size(), " pieces; only one is supported"));
  piece_ = pieces[0];
  for (const auto& [attr, out] :
       {std::pair{"NumberOfPoints", &num_points_}, std::pair{"NumberOfCells", &num_cells_}}) {
    const auto v = piece_->Attr(attr);
    const auto n = v ? ParseUint(*v) : std::nullopt;
    if (!n) return Error(absl::StrCat("Piece attribute ", attr, " is missing or not a count"));
    if (*n > kMaxCount)
      return Error(absl::StrCat("Piece ", attr, "=", *n, " exceeds the limit of ", kMaxCount));
    *out = *n;
  }
  if (appended_) {
    const auto appended = xml_.Children(root, "AppendedData");
    const auto enc = appended.empty() ? std::nullopt : appended[0]->Attr("encoding");
    if (enc == "base64") {
      appended_base64_ = true;
      // The encoded text up to the end of the file (the closing tags end it).
      appended_text_.resize(file_size_ - std::min(file_size_, appended_start_));
      FileSource src(fd_, appended_start_, file_size_);
      DECIMA_RETURN_IF_ERROR(
          src.Read(reinterpret_cast<uint8_t*>(appended_text_.data()), appended_text_.size()));
      const size_t end = appended_text_.find('<');
      if (end != std::string::npos) appended_text_.resize(end);
    } else if (enc != "raw") {
      return Error(absl::StrCat("AppendedData encoding '", enc.value_or("(missing)"),
                                "' is not raw or base64"));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<ArraySpec> VtuReader::Spec(const XmlElement& e, absl::string_view where) const {
  ArraySpec s;
  s.element = &e;
  s.name = std::string(e.Attr("Name").value_or(""));
  const std::string what = absl::StrCat(where, " DataArray '", s.name, "'");
  const auto type = e.Attr("type");
  const auto t = type ? ParseVtkType(*type) : std::nullopt;
  if (!t)
    return Error(absl::StrCat(what, " has type '", type.value_or("(missing)"),
                              "', expected an integer or float type such as Float32 or Int64"));
  s.type = *t;
  s.components = 1;
  if (const auto c = e.Attr("NumberOfComponents")) {
    const auto n = ParseUint(*c);
    if (!n || *n < 1 || *n > 9)
      return Error(absl::StrCat(what, " has NumberOfComponents '", *c, "'"));
    s.components = static_cast<int>(*n);
  }
  const auto format = e.Attr("format").value_or("");
  if (format == "ascii") {
    s.format = ArraySpec::kAscii;
  } else if (format == "binary") {
    s.format = ArraySpec::kBinary;
  } else if (format == "appended") {
    s.format = ArraySpec::kAppended;
    if (!appended_) return Error(absl::StrCat(what, " is appended but there is no <AppendedData>"));
    const auto off = e.Attr("offset");
    const auto o = off ? ParseUint(*off) : std::nullopt;
    if (!o) return Error(absl::StrCat(what, " has no valid offset attribute"));
    const uint64_t limit = appended_base64_ ? appended_text_.size() : file_size_ - appended_start_;
    if (*o >= limit)
      return Error(absl::StrCat(what, " offset ", *o, " is beyond the end of the file"));
    s.offset = *o;
  } else {
    return Error(
        absl::StrCat(what, " has format '", format, "', expected ascii, binary or appended"));
  }
  return s;
}

absl::StatusOr<const XmlElement*> VtuReader::FindArray(const XmlElement* section,
                                                       absl::string_view name,
                                                       absl::string_view section_name) const {
  if (section == nullptr) return nullptr;
  const XmlElement* found = nullptr;
  for (const XmlElement* e : xml_.Children(*section, "DataArray")) {
    if (e->Attr("Name") != name) continue;
    if (found != nullptr)
      return Error(absl::StrCat(section_name, " has two DataArrays named '", name, "'"));
    found = e;
  }
  return found;
}

absl::StatusOr<const XmlElement*> VtuReader::FieldArray(const XmlElement* point_data) const {
  const std::vector<const XmlElement*> arrays = point_data == nullptr
                                                    ? std::vector<const XmlElement*>{}
                                                    : xml_.Children(*point_data, "DataArray");
  // 1. The active scalars the file names: its own statement of which array is the field.
  if (const auto active = point_data == nullptr ? std::nullopt : point_data->Attr("Scalars")) {
    DECIMA_ASSIGN_OR_RETURN(const XmlElement* e, FindArray(point_data, *active, "PointData"));
    if (e == nullptr)
      return Error(absl::StrCat("PointData names '", *active,
                                "' as its active scalars, but has no DataArray of that name"));
    return e;
  }
  // 2. Decima's own name (files written before WriteVtu marked the active scalars).
  DECIMA_ASSIGN_OR_RETURN(const XmlElement* own, FindArray(point_data, "scalar", "PointData"));
  if (own != nullptr) return own;
  // 3. The only point array: nothing else it could be. It must have a name, which the report
  // gives as the field's source.
  if (arrays.size() == 1) {
    if (arrays[0]->Attr("Name").value_or("").empty())
      return Error(
          "PointData's only DataArray has no Name, so the field's source cannot be named "
          "(expected a Name attribute, e.g. Name=\"scalar\")");
    return arrays[0];
  }
  std::string names;
  for (const XmlElement* e : arrays)
    absl::StrAppend(&names, names.empty() ? "" : ", ", "'", e->Attr("Name").value_or(""), "'");
  if (arrays.empty())
    return Error(
        "PointData has no DataArray, so the file holds no field (expected active scalars, an "
        "array named 'scalar', or exactly one point array)");
  return Error(absl::StrCat("cannot tell which point array is the field: PointData has no active ",
                            "Scalars attribute and no array named 'scalar', but ", arrays.size(),
                            " arrays (", names, ")"));
}

absl::StatusOr<uint64_t> VtuReader::LoadBinary(ByteSource& src, uint64_t min_bytes,
                                               uint64_t max_bytes, uint64_t value_bytes,
                                               const std::function<uint8_t*(uint64_t)>& alloc) {
  auto header_word = [&]() -> absl::StatusOr<uint64_t> {
    uint64_t v = 0;
    DECIMA_RETURN_IF_ERROR(src.Read(reinterpret_cast<uint8_t*>(&v), header_bytes_));
    return v;
  };
  auto check_total = [&](uint64_t total) -> absl::Status {
    if (total < min_bytes || total > max_bytes || total % value_bytes != 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("holds ", total, " bytes, expected ",
                       min_bytes == max_bytes ? absl::StrCat(min_bytes)
                                              : absl::StrCat(min_bytes, " or ", max_bytes),
                       " for the Piece's counts"));
    }
    return absl::OkStatus();
  };
  if (!compressed_) {
    DECIMA_ASSIGN_OR_RETURN(const uint64_t n, header_word());
    DECIMA_RETURN_IF_ERROR(check_total(n));
    if (n > src.Remaining())
      return absl::InvalidArgumentError(
          absl::StrCat("truncated: holds ", n, " bytes but only ", src.Remaining(), " remain"));
    uint8_t* dst = alloc(n);
    DECIMA_RETURN_IF_ERROR(src.Read(dst, n));
    return n;
  }
  // vtkZLibDataCompressor and vtkLZMADataCompressor: [nblocks, block size, last partial size,
  // compressed sizes...], then the blocks (zlib streams, or .xz streams).
  const char* what = lzma_ ? "LZMA" : "zlib";
  const uint64_t max_ratio = lzma_ ? kMaxLzmaRatio : kMaxDeflateRatio;
  DECIMA_ASSIGN_OR_RETURN(const uint64_t nblocks, header_word());
  DECIMA_ASSIGN_OR_RETURN(const uint64_t block, header_word());
  DECIMA_ASSIGN_OR_RETURN(const uint64_t last, header_word());
  if (nblocks > src.Remaining() / header_bytes_)
    return absl::InvalidArgumentError(absl::StrCat("truncated: compression header claims ", nblocks,
                                                   " blocks, but only ", src.Remaining(),
                                                   " bytes remain"));
  if (nblocks > 0 && (block == 0 || last > block))
    return absl::InvalidArgumentError(
        absl::StrCat("compression header has block size ", block, " and last block size ", last));
  if (nblocks > 0 && (nblocks - 1) > std::numeric_limits<uint64_t>::max() / 2 / block)
    return absl::InvalidArgumentError("compression header sizes overflow");
  const uint64_t total = nblocks == 0 ? 0 : (nblocks - 1) * block + (last ? last : block);
  DECIMA_RETURN_IF_ERROR(check_total(total));
  std::vector<uint64_t> csize(nblocks);
  uint64_t csum = 0, cmax = 0;
  for (uint64_t b = 0; b < nblocks; ++b) {
    DECIMA_ASSIGN_OR_RETURN(csize[b], header_word());
    const uint64_t usize = (b + 1 == nblocks && last) ? last : block;
    if (usize / max_ratio > csize[b])
      return absl::InvalidArgumentError(absl::StrCat(what, " block ", b, " claims ", csize[b],
                                                     " compressed bytes for ", usize,
                                                     " bytes, an impossible ratio"));
    if (csize[b] > src.Remaining())
      return absl::InvalidArgumentError(absl::StrCat("truncated: ", what, " block ", b, " needs ",
                                                     csize[b], " bytes but only ", src.Remaining(),
                                                     " remain"));
    csum += csize[b];
    cmax = std::max(cmax, csize[b]);
  }
  if (csum > src.Remaining())
    return absl::InvalidArgumentError(absl::StrCat("truncated: ", what, " blocks need ", csum,
                                                   " bytes but only ", src.Remaining(), " remain"));
  uint8_t* dst = alloc(total);
  std::vector<uint8_t> in(cmax);
  for (uint64_t b = 0; b < nblocks; ++b) {
    const uint64_t usize = (b + 1 == nblocks && last) ? last : block;
    DECIMA_RETURN_IF_ERROR(src.Read(in.data(), csize[b]));
    if (lzma_) {
      uint64_t memlimit = kLzmaMemLimit;
      size_t in_pos = 0, out_pos = 0;
      const lzma_ret rc =
          lzma_stream_buffer_decode(&memlimit, 0, nullptr, in.data(), &in_pos, csize[b],
                                    dst + b * block, &out_pos, static_cast<size_t>(usize));
      if (rc != LZMA_OK || in_pos != csize[b] || out_pos != usize)
        return absl::InvalidArgumentError(
            absl::StrCat("LZMA block ", b, " is corrupt (",
                         rc == LZMA_MEMLIMIT_ERROR ? "needs more than 128 MiB to decode"
                         : rc != LZMA_OK ? absl::StrCat("liblzma error ", static_cast<int>(rc))
                                         : std::string("wrong size"),
                         ")"));
      continue;
    }
    uLongf out_len = static_cast<uLongf>(usize);
    const int rc = uncompress(dst + b * block, &out_len, in.data(), static_cast<uLong>(csize[b]));
    if (rc != Z_OK || out_len != usize)
      return absl::InvalidArgumentError(absl::StrCat("zlib block ", b, " is corrupt (",
                                                     rc != Z_OK ? zError(rc) : "wrong size", ")"));
  }
  return total;
}

absl::StatusOr<uint64_t> VtuReader::LoadAscii(const ArraySpec& spec, uint64_t min_bytes,
                                              uint64_t max_bytes,
                                              const std::function<uint8_t*(uint64_t)>& alloc) {
  const absl::string_view text = spec.element->text;
  const uint64_t size = TypeSize(spec.type);
  uint64_t tokens = 0;
  for (size_t i = 0; i < text.size();) {
    while (i < text.size() && IsSpace(text[i])) ++i;
    if (i == text.size()) break;
    ++tokens;
    while (i < text.size() && !IsSpace(text[i])) ++i;
  }
  const uint64_t total = tokens * size;
  if (total < min_bytes || total > max_bytes)
    return absl::InvalidArgumentError(
        absl::StrCat("holds ", tokens, " values, expected ", min_bytes / size,
                     max_bytes == min_bytes ? "" : absl::StrCat(" or ", max_bytes / size)));
  uint8_t* dst = alloc(total);
  const char* p = text.data();
  const char* end = p + text.size();
  for (uint64_t k = 0; k < tokens; ++k) {
    while (IsSpace(*p)) ++p;
    const char* b = p;
    while (p < end && !IsSpace(*p)) ++p;
    if (*b == '+') ++b;
    const bool ok = Dispatch(spec.type, [&](auto s) {
      using S = decltype(s);
      S v{};
      if constexpr (std::is_floating_point_v<S>) {
        auto r = std::from_chars(b, p, v);
        if (r.ec != std::errc() || r.ptr != p) return false;
      } else {
        auto r = std::from_chars(b, p, v);
        if (r.ec != std::errc() || r.ptr != p) return false;
      }
      std::memcpy(dst + k * sizeof(S), &v, sizeof(S));
      return true;
    });
    if (!ok)
      return absl::InvalidArgumentError(
          absl::StrCat("value ", k, " '", absl::string_view(b, p - b), "' is not a valid number"));
  }
  return total;
}

absl::StatusOr<uint64_t> VtuReader::LoadBytes(const ArraySpec& spec, uint64_t min_bytes,
                                              uint64_t max_bytes, uint64_t value_bytes,
                                              const std::function<uint8_t*(uint64_t)>& alloc) {
  switch (spec.format) {
    case ArraySpec::kAscii:
      return LoadAscii(spec, min_bytes, max_bytes, alloc);
    case ArraySpec::kBinary: {
      Base64Source src(spec.element->text.data(),
                       spec.element->text.data() + spec.element->text.size());
      return LoadBinary(src, min_bytes, max_bytes, value_bytes, alloc);
    }
    default:
      if (appended_base64_) {
        Base64Source src(appended_text_.data() + spec.offset,
                         appended_text_.data() + appended_text_.size());
        return LoadBinary(src, min_bytes, max_bytes, value_bytes, alloc);
      } else {
        FileSource src(fd_, appended_start_ + spec.offset, file_size_);
        return LoadBinary(src, min_bytes, max_bytes, value_bytes, alloc);
      }
  }
}

template <typename T>
absl::StatusOr<uint64_t> VtuReader::Load(const ArraySpec& spec, int components, uint64_t min_count,
                                         uint64_t max_count, std::vector<T>* out) {
  const std::string what = absl::StrCat("DataArray '", spec.name, "'");
  if (spec.components != components)
    return Error(
        absl::StrCat(what, " has ", spec.components, " components, expected ", components));
  const uint64_t size = TypeSize(spec.type);
  const uint64_t value_bytes = size * components;
  const bool same = spec.type == TypeOf<T>();
  std::vector<uint8_t> tmp;
  auto alloc = [&](uint64_t bytes) -> uint8_t* {
    if (same) {
      out->resize(bytes / sizeof(T));
      return reinterpret_cast<uint8_t*>(out->data());
    }
    tmp.resize(bytes);
    return tmp.data();
  };
  auto loaded =
      LoadBytes(spec, min_count * value_bytes, max_count * value_bytes, value_bytes, alloc);
  if (!loaded.ok()) return Annotate(loaded.status(), what);
  const uint64_t values = *loaded / size;
  if (!same) {
    out->resize(values);
    T* o = out->data();
    const absl::Status s = Dispatch(spec.type, [&](auto proto) -> absl::Status {
      using S = decltype(proto);
      const S* in = reinterpret_cast<const S*>(tmp.data());
      for (uint64_t i = 0; i < values; ++i) {
        const S v = in[i];
        if constexpr (std::is_integral_v<T>) {
          // Integer targets take only integral values in range.
          bool ok;
          if constexpr (std::is_floating_point_v<S>) {
            ok = std::isfinite(v) && v == std::floor(v) &&
                 v >= double(std::numeric_limits<T>::lowest()) &&
                 v <= double(std::numeric_limits<T>::max());
          } else {
            ok = std::in_range<T>(v);
          }
          if (!ok)
            return Error(absl::StrCat(what, " value ", i, " (", double(v), ") does not fit ",
                                      sizeof(T) == 1 ? "UInt8" : "Int32/Int64"));
          o[i] = static_cast<T>(v);
        } else {
          o[i] = static_cast<T>(v);
        }
      }
      return absl::OkStatus();
    });
    DECIMA_RETURN_IF_ERROR(s);
  }
  return values / components;
}

absl::StatusOr<TetMesh> VtuReader::Read() {
  DECIMA_RETURN_IF_ERROR(OpenAndReadHeader());
  DECIMA_RETURN_IF_ERROR(ParseHeader());
  const uint64_t nv = num_points_, nt = num_cells_;
  auto section = [&](absl::string_view name) -> absl::StatusOr<const XmlElement*> {
    const auto found = xml_.Children(*piece_, name);
    if (found.size() > 1) return Error(absl::StrCat("Piece has ", found.size(), " <", name, ">"));
    return found.empty() ? nullptr : found[0];
  };
  DECIMA_ASSIGN_OR_RETURN(const XmlElement* points, section("Points"));
  DECIMA_ASSIGN_OR_RETURN(const XmlElement* cells, section("Cells"));
  DECIMA_ASSIGN_OR_RETURN(const XmlElement* point_data, section("PointData"));
  DECIMA_ASSIGN_OR_RETURN(const XmlElement* cell_data, section("CellData"));
  if (points == nullptr) return Error("Piece has no <Points>");
  if (cells == nullptr) return Error("Piece has no <Cells>");

  TetMesh m;
  // Points first: they bound every later allocation through NumberOfPoints.
  {
    const auto arrays = xml_.Children(*points, "DataArray");
    if (arrays.size() != 1) return Error("<Points> must hold exactly one DataArray");
    DECIMA_ASSIGN_OR_RETURN(ArraySpec spec, Spec(*arrays[0], "Points"));
    spec.name = "Points";
    DECIMA_RETURN_IF_ERROR(Load(spec, 3, nv, nv, &m.positions).status());
    for (uint64_t i = 0; i < 3 * nv; ++i)
      if (!std::isfinite(m.positions[i]))
        return Error(absl::StrCat("point ", i / 3, " has a non-finite coordinate"));
  }
  // Cells: types, then offsets, then connectivity, so a mesh of other cells fails clearly.
  {
    auto get = [&](absl::string_view name) -> absl::StatusOr<ArraySpec> {
      DECIMA_ASSIGN_OR_RETURN(const XmlElement* e, FindArray(cells, name, "Cells"));
      if (e == nullptr) return Error(absl::StrCat("<Cells> has no DataArray '", name, "'"));
      return Spec(*e, "Cells");
    };
    DECIMA_ASSIGN_OR_RETURN(const ArraySpec types_spec, get("types"));
    std::vector<uint8_t> types;
    DECIMA_RETURN_IF_ERROR(Load(types_spec, 1, nt, nt, &types).status());
    for (uint64_t t = 0; t < nt; ++t) {
      if (types[t] != 10)
        return Unimplemented(absl::StrCat("cell ", t, " has VTK cell type ", int(types[t]),
                                          "; only tetrahedra (VTK_TETRA = 10) are supported"));
    }
    types = {};
    DECIMA_ASSIGN_OR_RETURN(const ArraySpec offsets_spec, get("offsets"));
    std::vector<int64_t> offsets;
    // VTK file version < 2 lists the end of each cell; 2.x adds a leading 0.
    DECIMA_ASSIGN_OR_RETURN(const uint64_t noff, Load(offsets_spec, 1, nt, nt + 1, &offsets));
    const uint64_t shift = noff == nt + 1 ? 1 : 0;
    if (shift && offsets[0] != 0) return Error("DataArray 'offsets' must start with 0");
    for (uint64_t t = 0; t < nt; ++t) {
      if (offsets[t + shift] != int64_t(4 * (t + 1)))
        return Error(absl::StrCat("DataArray 'offsets' entry ", t + shift, " is ",
                                  offsets[t + shift], ", expected ", 4 * (t + 1),
                                  " for a mesh of tetrahedra"));
    }
    offsets = {};
    DECIMA_ASSIGN_OR_RETURN(const ArraySpec conn_spec, get("connectivity"));
    DECIMA_RETURN_IF_ERROR(Load(conn_spec, 1, 4 * nt, 4 * nt, &m.tets).status());
  }
  for (uint64_t t = 0; t < nt; ++t) {
    const int32_t* v = &m.tets[4 * t];
    for (int q = 0; q < 4; ++q) {
      if (v[q] < 0 || uint64_t(v[q]) >= nv)
        return Error(absl::StrCat("cell ", t, " references point ", v[q], ", but there are ", nv,
                                  " points"));
      for (int r = 0; r < q; ++r)
        if (v[r] == v[q]) return Error(absl::StrCat("cell ", t, " uses point ", v[q], " twice"));
    }
    if (TetVolume(m, t) <= 0) {
      if (!options_.allow_inverted_cells)
        return Error(absl::StrCat("cell ", t, " is inverted or flat (signed volume ",
                                  TetVolume(m, t),
                                  " mm^3); tetrahedra must be positively oriented"));
      ++report.inverted_or_flat_cells;
    }
  }

  // Optional attributes.
  auto optional = [&](const XmlElement* sec, absl::string_view sec_name, absl::string_view name,
                      uint64_t count, auto* out) -> absl::StatusOr<bool> {
    DECIMA_ASSIGN_OR_RETURN(const XmlElement* e, FindArray(sec, name, sec_name));
    if (e == nullptr) return false;
    DECIMA_ASSIGN_OR_RETURN(const ArraySpec spec, Spec(*e, sec_name));
    DECIMA_RETURN_IF_ERROR(Load(spec, 1, count, count, out).status());
    return true;
  };
  // The field is never invented: a file whose field we cannot identify is an error, not zeros
  // (VTK's own filters call the array "scalars", and a silent all-zero field looked like a
  // valid but terrible mesh downstream).
  DECIMA_ASSIGN_OR_RETURN(const XmlElement* scalar_array, FieldArray(point_data));
  {
    DECIMA_ASSIGN_OR_RETURN(const ArraySpec spec, Spec(*scalar_array, "PointData"));
    DECIMA_RETURN_IF_ERROR(Load(spec, 1, nv, nv, &m.scalars).status());
    report.scalar_array = spec.name;
  }
  for (uint64_t v = 0; v < nv; ++v)
    if (!std::isfinite(m.scalars[v]))
      return Error(absl::StrCat("point ", v, " has a non-finite scalar"));
  DECIMA_ASSIGN_OR_RETURN(const bool has_labels,
                          optional(point_data, "PointData", "label", nv, &m.labels));
  if (!has_labels) m.labels.assign(nv, 0);
  report.has_labels = has_labels;
  for (uint64_t v = 0; v < nv; ++v)
    if (m.labels[v] >= kMaxRegions)
      return Error(absl::StrCat("point ", v, " has label ", int(m.labels[v]), ", expected 0..",
                                kMaxRegions - 1));
  DECIMA_ASSIGN_OR_RETURN(
      const bool has_distance,
      optional(point_data, "PointData", "interface_distance", nv, &m.interface_distance));
  if (!has_distance) m.interface_distance.assign(nv, std::numeric_limits<float>::infinity());
  report.has_interface_distance = has_distance;
  for (uint64_t v = 0; v < nv; ++v)
    if (std::isnan(m.interface_distance[v]))
      return Error(absl::StrCat("point ", v, " has a NaN interface_distance"));
  m.vertex_flags.assign(nv, 0);
  for (const auto& [name, bit] : {std::pair<absl::string_view, uint8_t>{"feature", kFeatureVertex},
                                  {"boundary", kExteriorBoundaryVertex}}) {
    std::vector<uint8_t> bits;
    DECIMA_ASSIGN_OR_RETURN(const bool has, optional(point_data, "PointData", name, nv, &bits));
    if (has)
      for (uint64_t v = 0; v < nv; ++v)
        if (bits[v]) m.vertex_flags[v] |= bit;
    report.has_vertex_flags = report.has_vertex_flags || has;
  }
  DECIMA_ASSIGN_OR_RETURN(const bool has_regions,
                          optional(cell_data, "CellData", "region", nt, &m.cell_regions));
  if (!has_regions) m.cell_regions.assign(nt, 0);
  report.has_regions = has_regions;
  for (uint64_t t = 0; t < nt; ++t)
    if (m.cell_regions[t] >= kMaxRegions)
      return Error(absl::StrCat("cell ", t, " has region ", int(m.cell_regions[t]),
                                ", expected 0..", kMaxRegions - 1));
  return m;
}

}  // namespace

absl::StatusOr<TetMesh> ReadVtu(const std::filesystem::path& path, VtuReadReport* report,
                                const VtuReadOptions& options) {
  VtuReader reader(path, options);
  auto mesh = reader.Read();
  if (mesh.ok() && report != nullptr) *report = reader.report;
  return mesh;
}

}  // namespace decima
