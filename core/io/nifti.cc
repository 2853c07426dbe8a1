// NIfTI-1 / NIfTI-2 reader and NIfTI-1 writer (own parser; see README.md for why not libnifti).
//
// Header layouts follow nifti1.h / nifti2.h (byte offsets below). Geometry follows the NIfTI-1
// standard's three methods: sform (method 3), qform quaternion (method 2), pixdim only
// (method 1); the result is converted from RAS to LPS by negating the first two rows.
#include <cmath>
#include <cstring>

#include "core/common/atomic_file.h"
#include "core/common/status.h"
#include "core/io/io_util.h"
#include "core/io/volume_io.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;
using internal::Invalid;
using internal::Unsupported;

constexpr int kNifti1HeaderSize = 348;
constexpr int kNifti2HeaderSize = 540;

// A NIfTI-1 or -2 header reduced to the fields Decima uses, widened to 64-bit/double.
struct NiftiHeader {
  int version = 1;
  bool swap = false;
  bool single_file = true;
  int64_t dim[8] = {};
  double pixdim[8] = {};
  int datatype = 0;
  int64_t vox_offset = 0;
  double scl_slope = 0;
  double scl_inter = 0;
  int qform_code = 0;
  int sform_code = 0;
  double quatern[3] = {};  // b, c, d
  double qoffset[3] = {};
  double srow[3][4] = {};
};

template <typename T>
T Get(const uint8_t* buf, size_t offset, bool swap) {
  T v;
  std::memcpy(&v, buf + offset, sizeof(T));
  if (swap) internal::SwapBytes(reinterpret_cast<uint8_t*>(&v), 1, sizeof(T));
  return v;
}

template <typename T>
void Put(uint8_t* buf, size_t offset, T v) {
  std::memcpy(buf + offset, &v, sizeof(T));
}

absl::StatusOr<VoxelType> TypeFromNifti(const fs::path& path, int datatype) {
  switch (datatype) {
    case 2:
      return VoxelType::kUInt8;
    case 4:
      return VoxelType::kInt16;
    case 8:
      return VoxelType::kInt32;
    case 16:
      return VoxelType::kFloat32;
    case 64:
      return VoxelType::kFloat64;
    case 256:
      return VoxelType::kInt8;
    case 512:
      return VoxelType::kUInt16;
    case 768:
      return VoxelType::kUInt32;
    case 32:
    case 128:
    case 1024:
    case 1280:
    case 1536:
    case 1792:
    case 2048:
    case 2304:
      return Unsupported(path, "datatype ", datatype,
                         " (complex, RGB, 64-bit integer or float128) is not supported; expected "
                         "uint8, int8, (u)int16, (u)int32, float32 or float64");
    default:
      return Invalid(path, "unknown datatype code ", datatype);
  }
}

int NiftiFromType(VoxelType type) {
  switch (type) {
    case VoxelType::kUInt8:
      return 2;
    case VoxelType::kInt16:
      return 4;
    case VoxelType::kInt32:
      return 8;
    case VoxelType::kFloat32:
      return 16;
    case VoxelType::kFloat64:
      return 64;
    case VoxelType::kInt8:
      return 256;
    case VoxelType::kUInt16:
      return 512;
    case VoxelType::kUInt32:
      return 768;
  }
  return 0;
}

// Parses the raw header bytes (already known to be 348 or 540 bytes long).
absl::StatusOr<NiftiHeader> ParseHeader(const fs::path& path, const uint8_t* b, int version,
                                        bool swap) {
  NiftiHeader h;
  h.version = version;
  h.swap = swap;
  if (version == 1) {
    const char* magic = reinterpret_cast<const char*>(b + 344);
    if (std::memcmp(magic, "n+1\0", 4) == 0) {
      h.single_file = true;
    } else if (std::memcmp(magic, "ni1\0", 4) == 0) {
      h.single_file = false;
    } else {
      return Unsupported(path,
                         "no NIfTI-1 magic ('n+1' or 'ni1') at byte 344: an ANALYZE 7.5 "
                         "file or not NIfTI; only NIfTI is supported");
    }
    for (int i = 0; i < 8; ++i) h.dim[i] = Get<int16_t>(b, 40 + 2 * i, swap);
    h.datatype = Get<int16_t>(b, 70, swap);
    for (int i = 0; i < 8; ++i) h.pixdim[i] = Get<float>(b, 76 + 4 * i, swap);
    const double vox = Get<float>(b, 108, swap);
    if (!std::isfinite(vox) || vox < 0 || vox != std::floor(vox) || vox > 1e15) {
      return Invalid(path, "vox_offset = ", vox, ", expected a non-negative whole byte offset");
    }
    h.vox_offset = static_cast<int64_t>(vox);
    h.scl_slope = Get<float>(b, 112, swap);
    h.scl_inter = Get<float>(b, 116, swap);
    h.qform_code = Get<int16_t>(b, 252, swap);
    h.sform_code = Get<int16_t>(b, 254, swap);
    for (int i = 0; i < 3; ++i) h.quatern[i] = Get<float>(b, 256 + 4 * i, swap);
    for (int i = 0; i < 3; ++i) h.qoffset[i] = Get<float>(b, 268 + 4 * i, swap);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 4; ++c) h.srow[r][c] = Get<float>(b, 280 + 16 * r + 4 * c, swap);
    }
  } else {
    const char* magic = reinterpret_cast<const char*>(b + 4);
    if (std::memcmp(magic, "n+2\0\r\n\032\n", 8) == 0) {
      h.single_file = true;
    } else if (std::memcmp(magic, "ni2\0\r\n\032\n", 8) == 0) {
      h.single_file = false;
    } else {
      return Invalid(path,
                     "sizeof_hdr is 540 but the NIfTI-2 magic ('n+2' or 'ni2' followed "
                     "by \\r\\n\\032\\n) is missing or damaged");
    }
    h.datatype = Get<int16_t>(b, 12, swap);
    for (int i = 0; i < 8; ++i) h.dim[i] = Get<int64_t>(b, 16 + 8 * i, swap);
    for (int i = 0; i < 8; ++i) h.pixdim[i] = Get<double>(b, 104 + 8 * i, swap);
    h.vox_offset = Get<int64_t>(b, 168, swap);
    if (h.vox_offset < 0) {
      return Invalid(path, "vox_offset = ", h.vox_offset, ", expected >= 0");
    }
    h.scl_slope = Get<double>(b, 176, swap);
    h.scl_inter = Get<double>(b, 184, swap);
    h.qform_code = Get<int32_t>(b, 344, swap);
    h.sform_code = Get<int32_t>(b, 348, swap);
    for (int i = 0; i < 3; ++i) h.quatern[i] = Get<double>(b, 352 + 8 * i, swap);
    for (int i = 0; i < 3; ++i) h.qoffset[i] = Get<double>(b, 376 + 8 * i, swap);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 4; ++c) h.srow[r][c] = Get<double>(b, 400 + 32 * r + 8 * c, swap);
    }
  }
  return h;
}

// Reads and parses the header at the start of `path` (gzip detected by magic bytes).
absl::StatusOr<NiftiHeader> ReadHeader(const fs::path& path) {
  DECIMA_ASSIGN_OR_RETURN(const std::string head, internal::ReadFileHead(path, 2));
  if (head.empty()) return Invalid(path, "empty file, expected a NIfTI header");
  const bool gz = internal::HasGzipMagic(head);
  DECIMA_ASSIGN_OR_RETURN(
      auto in, internal::InputStream::Open(path, 0,
                                           gz ? internal::InputStream::Compression::kZlibOrGzip
                                              : internal::InputStream::Compression::kNone));
  uint8_t buf[kNifti2HeaderSize] = {};
  DECIMA_RETURN_IF_ERROR(in.ReadExact(buf, 4, "NIfTI header"));
  const int32_t size = Get<int32_t>(buf, 0, false);
  const int32_t swapped = Get<int32_t>(buf, 0, true);
  int version = 0;
  bool swap = false;
  if (size == kNifti1HeaderSize || swapped == kNifti1HeaderSize) {
    version = 1;
    swap = size != kNifti1HeaderSize;
  } else if (size == kNifti2HeaderSize || swapped == kNifti2HeaderSize) {
    version = 2;
    swap = size != kNifti2HeaderSize;
  } else {
    return Invalid(path, "sizeof_hdr = ", size, ", expected 348 (NIfTI-1) or 540 (NIfTI-2)");
  }
  const int header_size = version == 1 ? kNifti1HeaderSize : kNifti2HeaderSize;
  DECIMA_RETURN_IF_ERROR(in.ReadExact(buf + 4, header_size - 4, "NIfTI header"));
  return ParseHeader(path, buf, version, swap);
}

// For a .hdr/.img pair: the name of the partner file, trying both with and without ".gz".
fs::path Partner(const fs::path& path, const std::string& from, const std::string& to) {
  const std::string name = path.filename().string();
  const std::string lower = internal::LowerName(path);
  const bool gz = internal::EndsWith(lower, ".gz");
  const size_t stem_len = name.size() - from.size() - (gz ? 3 : 0);
  const std::string stem = name.substr(0, stem_len);
  const fs::path same = path.parent_path() / (stem + to + (gz ? ".gz" : ""));
  const fs::path other = path.parent_path() / (stem + to + (gz ? "" : ".gz"));
  std::error_code ec;
  if (!fs::exists(same, ec) && fs::exists(other, ec)) return other;
  return same;
}

// Direction (RAS, orthonormal columns) and origin (RAS) per the NIfTI methods 3, 2, 1.
absl::Status Geometry(const fs::path& path, const NiftiHeader& h, Eigen::Matrix3d& dir,
                      Eigen::Vector3d& origin) {
  if (h.sform_code > 0) {
    Eigen::Matrix3d m;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) m(r, c) = h.srow[r][c];
      origin[r] = h.srow[r][3];
    }
    bool ok = m.allFinite() && origin.allFinite();
    for (int c = 0; ok && c < 3; ++c) {
      const double n = m.col(c).norm();
      if (!(n > 0))
        ok = false;
      else
        m.col(c) /= n;
    }
    if (ok && (m.transpose() * m).isIdentity(1e-3)) {
      dir = m;
      return absl::OkStatus();
    }
    if (h.qform_code <= 0) {
      return Invalid(path,
                     "sform (srow_x/y/z) is not a finite rotation times scaling (zero, "
                     "sheared or non-finite columns) and no qform to fall back on");
    }
    // A sheared sform cannot be a Volume's direction; the qform is rigid by construction.
  }
  if (h.qform_code > 0) {
    double b = h.quatern[0], c = h.quatern[1], d = h.quatern[2];
    for (int i = 0; i < 3; ++i) origin[i] = h.qoffset[i];
    if (!std::isfinite(b) || !std::isfinite(c) || !std::isfinite(d) || !origin.allFinite()) {
      return Invalid(path, "qform quaternion or qoffset is not finite");
    }
    double a = 1.0 - (b * b + c * c + d * d);
    if (a < 1e-7) {  // nifti1.h: (b, c, d) of unit length means a 180 degree rotation
      const double s = 1.0 / std::sqrt(b * b + c * c + d * d);
      b *= s, c *= s, d *= s;
      a = 0;
    } else {
      a = std::sqrt(a);
    }
    dir = Eigen::Quaterniond(a, b, c, d).normalized().toRotationMatrix();
    if (h.pixdim[0] < 0) dir.col(2) *= -1;  // qfac
    return absl::OkStatus();
  }
  dir.setIdentity();
  origin.setZero();
  return absl::OkStatus();
}

template <typename T>
void Rescale(const uint8_t* src, size_t n, double slope, double inter, float* dst) {
  for (size_t i = 0; i < n; ++i) {
    T v;
    std::memcpy(&v, src + i * sizeof(T), sizeof(T));
    dst[i] = static_cast<float>(static_cast<double>(v) * slope + inter);
  }
}

void RescaleToFloat(Volume& v, double slope, double inter) {
  const size_t n = static_cast<size_t>(v.voxel_count());
  std::vector<uint8_t> out(n * sizeof(float));
  float* dst = reinterpret_cast<float*>(out.data());
  const uint8_t* src = v.bytes.data();
  switch (v.type) {
    case VoxelType::kUInt8:
      Rescale<uint8_t>(src, n, slope, inter, dst);
      break;
    case VoxelType::kInt8:
      Rescale<int8_t>(src, n, slope, inter, dst);
      break;
    case VoxelType::kUInt16:
      Rescale<uint16_t>(src, n, slope, inter, dst);
      break;
    case VoxelType::kInt16:
      Rescale<int16_t>(src, n, slope, inter, dst);
      break;
    case VoxelType::kUInt32:
      Rescale<uint32_t>(src, n, slope, inter, dst);
      break;
    case VoxelType::kInt32:
      Rescale<int32_t>(src, n, slope, inter, dst);
      break;
    case VoxelType::kFloat32:
      Rescale<float>(src, n, slope, inter, dst);
      break;
    case VoxelType::kFloat64:
      Rescale<double>(src, n, slope, inter, dst);
      break;
  }
  v.bytes = std::move(out);
  v.type = VoxelType::kFloat32;
}

}  // namespace

namespace internal {

absl::StatusOr<Volume> ReadNifti(const fs::path& path, ReadMode mode) {
  const std::string lower = internal::LowerName(path);
  const std::string base =
      internal::EndsWith(lower, ".gz") ? lower.substr(0, lower.size() - 3) : lower;
  fs::path header_path = path;
  fs::path data_path = path;
  if (internal::EndsWith(base, ".hdr")) {
    data_path = Partner(path, ".hdr", ".img");
  } else if (internal::EndsWith(base, ".img")) {
    header_path = Partner(path, ".img", ".hdr");
  }
  DECIMA_ASSIGN_OR_RETURN(const NiftiHeader h, ReadHeader(header_path));
  const int header_size = h.version == 1 ? kNifti1HeaderSize : kNifti2HeaderSize;
  if (h.single_file && header_path != data_path) {
    return Invalid(header_path, "header says single-file NIfTI ('n+", h.version,
                   "') but was given as a .hdr/.img pair");
  }
  if (!h.single_file && header_path == data_path) {
    return Invalid(path, "header says the data is in a separate .img file ('ni", h.version,
                   "'); open the .hdr next to it");
  }

  // Dimensions: 3D scalar only.
  const int64_t ndim = h.dim[0];
  if (ndim < 1 || ndim > 7) {
    return Invalid(header_path, "dim[0] = ", ndim, ", expected 1..7 (number of dimensions)");
  }
  if (ndim < 3) {
    return Invalid(header_path, "2D image: Decima needs a 3D volume (dim[0] = ", ndim, ")");
  }
  for (int i = 4; i <= ndim; ++i) {
    if (h.dim[i] != 1) {
      return Unsupported(header_path, "dim[", i, "] = ", h.dim[i],
                         ": only 3D scalar volumes are supported (4D series or vector data "
                         "are not)");
    }
  }
  const std::array<int64_t, 3> dims{h.dim[1], h.dim[2], h.dim[3]};
  DECIMA_RETURN_IF_ERROR(internal::CheckDims(header_path, dims, "dim[1..3]"));
  DECIMA_ASSIGN_OR_RETURN(const VoxelType type, TypeFromNifti(header_path, h.datatype));

  Volume v;
  v.dims = dims;
  v.type = type;
  for (int c = 0; c < 3; ++c) {
    const double s = std::abs(h.pixdim[c + 1]);
    if (!std::isfinite(s) || s <= 0) {
      return Invalid(header_path, "pixdim[", c + 1, "] = ", h.pixdim[c + 1],
                     ", expected a finite non-zero voxel size");
    }
    v.spacing[c] = s;
  }
  Eigen::Matrix3d dir;
  Eigen::Vector3d origin;
  DECIMA_RETURN_IF_ERROR(Geometry(header_path, h, dir, origin));
  // RAS -> LPS.
  const Eigen::Vector3d flip(-1, -1, 1);
  v.direction = flip.asDiagonal() * dir;
  v.origin = flip.cwiseProduct(origin);

  // Data.
  int64_t offset = h.vox_offset;
  if (h.single_file && offset < header_size) {
    return Invalid(header_path, "vox_offset = ", offset, " lies inside the ", header_size,
                   "-byte header");
  }
  DECIMA_ASSIGN_OR_RETURN(const std::string head, internal::ReadFileHead(data_path, 2));
  const bool gz = internal::HasGzipMagic(head);
  const bool rescale =
      std::isfinite(h.scl_slope) && h.scl_slope != 0 && !(h.scl_slope == 1 && h.scl_inter == 0);
  if (mode == ReadMode::kHeaderOnly) {
    DECIMA_RETURN_IF_ERROR(
        internal::CheckVoxelBytes(data_path, gz ? 0 : offset, gz, gz ? offset : 0,
                                  internal::DataBytes(dims, type), "voxel data"));
    if (rescale) v.type = VoxelType::kFloat32;  // what the full read returns
    return v;
  }
  DECIMA_ASSIGN_OR_RETURN(v.bytes,
                          internal::ReadVoxelBytes(data_path, gz ? 0 : offset, gz, gz ? offset : 0,
                                                   internal::DataBytes(dims, type), "voxel data"));
  if (h.swap) {
    internal::SwapBytes(v.bytes.data(), static_cast<size_t>(v.voxel_count()), VoxelTypeSize(type));
  }
  // scl_slope = 0 means "no scaling" (nifti1.h); a non-finite slope is treated the same way
  // rather than poisoning every voxel with NaN.
  if (rescale) {
    if (!std::isfinite(h.scl_inter)) {
      return Invalid(header_path, "scl_inter = ", h.scl_inter, ", expected a finite number");
    }
    RescaleToFloat(v, h.scl_slope, h.scl_inter);
  }
  DECIMA_RETURN_IF_ERROR(Validate(v, path.string()));
  return v;
}

}  // namespace internal

absl::StatusOr<Volume> ReadNifti(const fs::path& path) {
  return internal::ReadNifti(path, internal::ReadMode::kVolume);
}

absl::Status WriteNifti(const Volume& volume, const fs::path& path) {
  DECIMA_RETURN_IF_ERROR(Validate(volume, path.string()));
  const std::string lower = internal::LowerName(path);
  const bool gz = internal::EndsWith(lower, ".nii.gz");
  if (!gz && !internal::EndsWith(lower, ".nii")) {
    return Invalid(path, "NIfTI output needs the extension .nii or .nii.gz");
  }
  for (int c = 0; c < 3; ++c) {
    if (volume.dims[c] > 32767) {
      return Invalid(path, "dimension ", c, " = ", volume.dims[c],
                     " exceeds NIfTI-1's limit of 32767");
    }
  }
  // NIfTI-1 header + 4-byte extension flag (all zero: no extensions), data at byte 352.
  uint8_t hdr[352] = {};
  Put<int32_t>(hdr, 0, kNifti1HeaderSize);
  Put<char>(hdr, 38, 'r');  // "regular", as ANALYZE readers expect
  Put<int16_t>(hdr, 40, 3);
  for (int c = 0; c < 3; ++c) Put<int16_t>(hdr, 42 + 2 * c, static_cast<int16_t>(volume.dims[c]));
  for (int i = 4; i < 8; ++i) Put<int16_t>(hdr, 40 + 2 * i, 1);
  Put<int16_t>(hdr, 70, static_cast<int16_t>(NiftiFromType(volume.type)));
  Put<int16_t>(hdr, 72, static_cast<int16_t>(8 * VoxelTypeSize(volume.type)));

  // LPS -> RAS, then split the rotation into a proper rotation and qfac (nifti1.h method 2).
  const Eigen::Vector3d flip(-1, -1, 1);
  const Eigen::Matrix3d dir = flip.asDiagonal() * volume.direction;
  const Eigen::Vector3d origin = flip.cwiseProduct(volume.origin);
  Eigen::Matrix3d rot = dir;
  float qfac = 1;
  if (rot.determinant() < 0) {
    qfac = -1;
    rot.col(2) *= -1;
  }
  Eigen::Quaterniond q(rot);
  q.normalize();
  if (q.w() < 0) q.coeffs() *= -1;

  Put<float>(hdr, 76, qfac);
  for (int c = 0; c < 3; ++c) Put<float>(hdr, 80 + 4 * c, static_cast<float>(volume.spacing[c]));
  for (int i = 4; i < 8; ++i) Put<float>(hdr, 76 + 4 * i, 1.0f);
  Put<float>(hdr, 108, 352.0f);
  Put<float>(hdr, 112, 1.0f);  // scl_slope 1, scl_inter 0: values are stored as they are
  Put<char>(hdr, 123, 2);      // xyzt_units: NIFTI_UNITS_MM
  const std::string descrip = "Decima";
  std::memcpy(hdr + 148, descrip.data(), descrip.size());
  Put<int16_t>(hdr, 252, 1);  // qform_code: NIFTI_XFORM_SCANNER_ANAT
  Put<int16_t>(hdr, 254, 1);  // sform_code: NIFTI_XFORM_SCANNER_ANAT
  Put<float>(hdr, 256, static_cast<float>(q.x()));
  Put<float>(hdr, 260, static_cast<float>(q.y()));
  Put<float>(hdr, 264, static_cast<float>(q.z()));
  for (int r = 0; r < 3; ++r) Put<float>(hdr, 268 + 4 * r, static_cast<float>(origin[r]));
  const Eigen::Matrix3d affine = dir * volume.spacing.asDiagonal();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      Put<float>(hdr, 280 + 16 * r + 4 * c, static_cast<float>(affine(r, c)));
    }
    Put<float>(hdr, 280 + 16 * r + 12, static_cast<float>(origin[r]));
  }
  std::memcpy(hdr + 344, "n+1\0", 4);

  AtomicFile out;
  DECIMA_RETURN_IF_ERROR(out.Open(path));
  if (gz) {
    DECIMA_ASSIGN_OR_RETURN(
        const std::vector<uint8_t> z,
        internal::Deflate({{hdr, sizeof(hdr)}, {volume.bytes.data(), volume.bytes.size()}},
                          /*gzip=*/true, 6, path));
    DECIMA_RETURN_IF_ERROR(out.Write(z.data(), z.size()));
  } else {
    DECIMA_RETURN_IF_ERROR(out.Write(hdr, sizeof(hdr)));
    DECIMA_RETURN_IF_ERROR(out.Write(volume.bytes.data(), volume.bytes.size()));
  }
  return out.Commit();
}

}  // namespace decima::io
