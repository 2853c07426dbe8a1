#include "core/io/dicom_export.h"

// clang-format off
#include "dcmtk/config/osconfig.h"  // must come first
// clang-format on
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmfg/fgderimg.h"
#include "dcmtk/dcmfg/fgfracon.h"
#include "dcmtk/dcmfg/fgpixmsr.h"
#include "dcmtk/dcmfg/fgplanor.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmiod/cielabutil.h"
#include "dcmtk/dcmiod/iodreferences.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <memory>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "core/io/dicom.h"
#include "core/io/png.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;

constexpr const char* kScSopClass = "1.2.840.10008.5.1.4.1.1.7";

struct SourceSlice {
  fs::path file;
  std::string sop_class_uid, sop_instance_uid;
  std::string position_text;  // ImagePositionPatient as stored (copied to the SEG frame)
  Eigen::Vector3d position{0, 0, 0};
  double along_normal = 0;
};

struct SourceSeries {
  std::vector<SourceSlice> slices;       // sorted along the normal, like ReadDicomSeries
  std::unique_ptr<DcmFileFormat> first;  // header of one instance: patient, study, FoR
  std::string study_uid, series_uid, patient_id, orientation_text, pixel_spacing_text,
      slice_thickness_text;
  Eigen::Vector3d row{1, 0, 0}, col{0, 1, 0}, normal{0, 0, 1};
  long rows = 0, columns = 0;
};

absl::Status DcmError(const std::string& what, const OFCondition& c) {
  return absl::InternalError(absl::StrCat(what, ": ", c.text()));
}

std::string Str(DcmItem& item, const DcmTagKey& tag, bool all_values = false) {
  OFString v;
  if (all_values) {
    item.findAndGetOFStringArray(tag, v);
  } else {
    item.findAndGetOFString(tag, v);
  }
  return std::string(v.c_str());
}

absl::StatusOr<std::vector<double>> Numbers(const std::string& text, size_t count,
                                            const std::string& where) {
  std::vector<double> out;
  for (absl::string_view part : absl::StrSplit(text, '\\')) {
    double v = 0;
    if (!absl::SimpleAtod(part, &v) || !std::isfinite(v)) break;
    out.push_back(v);
  }
  if (out.size() != count) {
    return absl::InvalidArgumentError(
        absl::StrCat(where, ": '", text, "', expected ", count, " numbers"));
  }
  return out;
}

absl::StatusOr<SourceSeries> ReadSource(const fs::path& dir, const std::string& uid) {
  SourceSeries s;
  std::error_code ec;
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(dir, ec)) {
    if (e.is_regular_file(ec)) files.push_back(e.path());
  }
  if (ec) return absl::InvalidArgumentError(absl::StrCat(dir.string(), ": ", ec.message()));
  std::sort(files.begin(), files.end());
  for (const auto& f : files) {
    std::string why;
    if (!HasDicomMarker(f, &why)) continue;
    auto ff = std::make_unique<DcmFileFormat>();
    OFCondition c = ff->loadFileUntilTag(f.c_str(), EXS_Unknown, EGL_noChange, DCM_MaxReadLength,
                                         ERM_autoDetect, DCM_PixelData);
    if (c.bad()) return DcmError(f.string(), c);
    DcmDataset& d = *ff->getDataset();
    const std::string series = Str(d, DCM_SeriesInstanceUID);
    if (series.empty() || (!uid.empty() && series != uid)) continue;
    if (!d.tagExists(DCM_Rows)) continue;
    if (!s.series_uid.empty() && series != s.series_uid) {
      return absl::InvalidArgumentError(absl::StrCat(
          dir.string(), ": several series (", s.series_uid, ", ", series, ") and no uid given"));
    }
    SourceSlice slice;
    slice.file = f;
    slice.sop_class_uid = Str(d, DCM_SOPClassUID);
    slice.sop_instance_uid = Str(d, DCM_SOPInstanceUID);
    slice.position_text = Str(d, DCM_ImagePositionPatient, true);
    auto p = Numbers(slice.position_text, 3, f.string() + " ImagePositionPatient");
    if (!p.ok()) return p.status();
    slice.position = {(*p)[0], (*p)[1], (*p)[2]};
    if (slice.sop_instance_uid.empty() || slice.sop_class_uid.empty()) {
      return absl::InvalidArgumentError(absl::StrCat(f.string(), ": no SOP Class/Instance UID"));
    }
    if (s.series_uid.empty()) {
      s.series_uid = series;
      s.study_uid = Str(d, DCM_StudyInstanceUID);
      s.patient_id = Str(d, DCM_PatientID);
      s.orientation_text = Str(d, DCM_ImageOrientationPatient, true);
      s.pixel_spacing_text = Str(d, DCM_PixelSpacing, true);
      s.slice_thickness_text = Str(d, DCM_SliceThickness);
      Uint16 r = 0, cols = 0;
      d.findAndGetUint16(DCM_Rows, r);
      d.findAndGetUint16(DCM_Columns, cols);
      s.rows = r;
      s.columns = cols;
      auto o = Numbers(s.orientation_text, 6, f.string() + " ImageOrientationPatient");
      if (!o.ok()) return o.status();
      s.row = Eigen::Vector3d((*o)[0], (*o)[1], (*o)[2]).normalized();
      s.col = Eigen::Vector3d((*o)[3], (*o)[4], (*o)[5]).normalized();
      s.normal = s.row.cross(s.col).normalized();
      if (auto ps = Numbers(s.pixel_spacing_text, 2, f.string() + " PixelSpacing"); !ps.ok()) {
        return ps.status();
      }
      s.first = std::move(ff);
    }
    s.slices.push_back(std::move(slice));
  }
  if (s.slices.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(dir.string(), ": no image instance", uid.empty() ? "" : " of series " + uid));
  }
  for (auto& sl : s.slices) sl.along_normal = sl.position.dot(s.normal);
  std::sort(s.slices.begin(), s.slices.end(), [](const SourceSlice& a, const SourceSlice& b) {
    return a.along_normal < b.along_normal;
  });
  return s;
}

// DICOM DA and TM of now (local time, as modalities write them).
void Now(std::string* date, std::string* time) {
  const std::time_t t = std::time(nullptr);
  std::tm tm{};
  localtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y%m%d", &tm);
  *date = buf;
  std::strftime(buf, sizeof buf, "%H%M%S", &tm);
  *time = buf;
}

// Patient and study attributes every object of the study carries, copied from the source.
const DcmTagKey kCopiedTags[] = {DCM_SpecificCharacterSet,
                                 DCM_PatientName,
                                 DCM_PatientID,
                                 DCM_PatientBirthDate,
                                 DCM_PatientSex,
                                 DCM_StudyInstanceUID,
                                 DCM_StudyDate,
                                 DCM_StudyTime,
                                 DCM_ReferringPhysicianName,
                                 DCM_StudyID,
                                 DCM_AccessionNumber,
                                 DCM_StudyDescription};

// Attributes of the Patient, General Study and (type 2) empty ones every object of the study
// carries, copied from the source.
void CopyPatientAndStudy(DcmDataset* source, DcmDataset* d) {
  for (const DcmTagKey& tag : kCopiedTags) {
    OFString v;
    if (source->findAndGetOFStringArray(tag, v).good()) d->putAndInsertOFStringArray(tag, v);
  }
  for (const DcmTagKey& tag :
       {DCM_PatientName, DCM_PatientID, DCM_PatientBirthDate, DCM_PatientSex, DCM_StudyDate,
        DCM_StudyTime, DCM_ReferringPhysicianName, DCM_StudyID, DCM_AccessionNumber}) {
    if (!d->tagExists(tag)) d->insertEmptyElement(tag);
  }
}

absl::Status WriteSecondaryCapture(const SourceSeries& src, const fs::path& png,
                                   const std::string& series_uid, int number, const fs::path& out) {
  auto image = ReadPng(png);
  if (!image.ok()) return image.status();
  DcmFileFormat ff;
  DcmDataset* d = ff.getDataset();
  CopyPatientAndStudy(src.first->getDataset(), d);
  std::string date, time;
  Now(&date, &time);
  const std::string sop_uid = NewDicomUid();
  d->putAndInsertString(DCM_SOPClassUID, kScSopClass);
  d->putAndInsertString(DCM_SOPInstanceUID, sop_uid.c_str());
  d->putAndInsertString(DCM_SeriesInstanceUID, series_uid.c_str());
  d->putAndInsertString(DCM_Modality, "OT");
  d->putAndInsertString(DCM_SeriesNumber, "9002");
  d->putAndInsertString(DCM_SeriesDescription, "Decima renders");
  d->putAndInsertString(DCM_InstanceNumber, std::to_string(number).c_str());
  d->putAndInsertString(DCM_ConversionType, "WSD");
  d->putAndInsertString(DCM_Manufacturer, "Decima");
  d->putAndInsertString(DCM_ImageType, "DERIVED\\SECONDARY");
  d->putAndInsertString(DCM_ContentDate, date.c_str());
  d->putAndInsertString(DCM_ContentTime, time.c_str());
  d->putAndInsertString(DCM_DateOfSecondaryCapture, date.c_str());
  d->putAndInsertString(DCM_TimeOfSecondaryCapture, time.c_str());
  d->putAndInsertString(DCM_DerivationDescription,
                        absl::StrCat("Decima render ", png.filename().string()).c_str());
  d->insertEmptyElement(DCM_PatientOrientation);
  d->insertEmptyElement(DCM_Laterality);  // type 2C; empty: a render shows no single side
  d->putAndInsertString(DCM_BurnedInAnnotation, "NO");
  d->putAndInsertUint16(DCM_SamplesPerPixel, 3);
  d->putAndInsertString(DCM_PhotometricInterpretation, "RGB");
  d->putAndInsertUint16(DCM_PlanarConfiguration, 0);
  d->putAndInsertUint16(DCM_Rows, static_cast<Uint16>(image->height));
  d->putAndInsertUint16(DCM_Columns, static_cast<Uint16>(image->width));
  d->putAndInsertUint16(DCM_BitsAllocated, 8);
  d->putAndInsertUint16(DCM_BitsStored, 8);
  d->putAndInsertUint16(DCM_HighBit, 7);
  d->putAndInsertUint16(DCM_PixelRepresentation, 0);
  // The source series the picture was made from.
  DcmItem* ref = nullptr;
  if (d->findOrCreateSequenceItem(DCM_SourceImageSequence, ref, -2).good() && ref != nullptr) {
    ref->putAndInsertString(DCM_ReferencedSOPClassUID, src.slices[0].sop_class_uid.c_str());
    ref->putAndInsertString(DCM_ReferencedSOPInstanceUID, src.slices[0].sop_instance_uid.c_str());
  }
  d->putAndInsertUint8Array(DCM_PixelData, image->pixels.data(),
                            static_cast<unsigned long>(image->pixels.size()));
  OFCondition c = ff.saveFile(out.c_str(), EXS_LittleEndianExplicit);
  if (c.bad()) return DcmError(out.string(), c);
  return absl::OkStatus();
}

constexpr const char* kEncapsulatedStlSopClass = "1.2.840.10008.5.1.4.1.1.104.3";

// The bytes of a binary STL, checked to be one (84-byte header and count, 50 bytes a triangle).
absl::StatusOr<std::string> ReadBinaryStl(const fs::path& path) {
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) return absl::NotFoundError(absl::StrCat(path.string(), ": cannot open"));
  std::string bytes;
  char buf[1 << 16];
  for (size_t n; (n = std::fread(buf, 1, sizeof buf, f)) > 0;) bytes.append(buf, n);
  std::fclose(f);
  uint32_t triangles = 0;
  if (bytes.size() >= 84) std::memcpy(&triangles, bytes.data() + 80, 4);
  // OB values are at most 2^32 - 2 bytes; a surface that large is no job's.
  if (bytes.size() < 84 || bytes.size() != 84 + 50 * uint64_t{triangles} ||
      bytes.size() >= (uint64_t{1} << 32) - 2) {
    return absl::InvalidArgumentError(absl::StrCat(
        path.string(), ": not a binary STL (", bytes.size(), " bytes for ", triangles,
        " triangles; expected 84 + 50 per triangle)"));
  }
  return bytes;
}

// One Encapsulated STL instance (PS3.3 A.85): the Encapsulated Document Series, Frame of
// Reference, Enhanced General Equipment and Manufacturing 3D Model modules around the file.
absl::Status WriteEncapsulatedStl(const SourceSeries& src, const std::string& frame_of_reference,
                                  const DicomExportOptions::Surface& surface,
                                  const std::string& series_uid, int number, const fs::path& out) {
  auto stl = ReadBinaryStl(surface.stl);
  if (!stl.ok()) return stl.status();
  DcmFileFormat ff;
  DcmDataset* d = ff.getDataset();
  CopyPatientAndStudy(src.first->getDataset(), d);
  std::string date, time;
  Now(&date, &time);
  d->putAndInsertString(DCM_SOPClassUID, kEncapsulatedStlSopClass);
  d->putAndInsertString(DCM_SOPInstanceUID, NewDicomUid().c_str());
  d->putAndInsertString(DCM_SeriesInstanceUID, series_uid.c_str());
  d->putAndInsertString(DCM_Modality, "M3D");
  d->putAndInsertString(DCM_SeriesNumber, "9003");
  d->putAndInsertString(DCM_SeriesDescription, "Decima region surfaces");
  d->putAndInsertString(DCM_InstanceNumber, std::to_string(number).c_str());
  d->putAndInsertString(DCM_FrameOfReferenceUID, frame_of_reference.c_str());
  d->insertEmptyElement(DCM_PositionReferenceIndicator);
  d->putAndInsertString(DCM_Manufacturer, "Decima");
  d->putAndInsertString(DCM_ManufacturerModelName, "decima-server");
  d->putAndInsertString(DCM_DeviceSerialNumber, "0");
  d->putAndInsertString(DCM_SoftwareVersions, "decima");
  DcmItem* unit = nullptr;
  if (d->findOrCreateSequenceItem(DCM_MeasurementUnitsCodeSequence, unit, -2).good() &&
      unit != nullptr) {
    unit->putAndInsertString(DCM_CodeValue, "mm");
    unit->putAndInsertString(DCM_CodingSchemeDesignator, "UCUM");
    unit->putAndInsertString(DCM_CodeMeaning, "millimeter");
  }
  d->putAndInsertString(DCM_ContentDate, date.c_str());
  d->putAndInsertString(DCM_ContentTime, time.c_str());
  d->putAndInsertString(DCM_AcquisitionDateTime, (date + time).c_str());
  d->putAndInsertString(DCM_BurnedInAnnotation, "NO");
  d->putAndInsertString(DCM_DocumentTitle, surface.name.c_str());
  d->insertEmptyElement(DCM_ConceptNameCodeSequence);
  // The series the surface was made from.
  DcmItem* ref = nullptr;
  if (d->findOrCreateSequenceItem(DCM_SourceInstanceSequence, ref, -2).good() && ref != nullptr) {
    ref->putAndInsertString(DCM_ReferencedSOPClassUID, src.slices[0].sop_class_uid.c_str());
    ref->putAndInsertString(DCM_ReferencedSOPInstanceUID, src.slices[0].sop_instance_uid.c_str());
  }
  // Common Instance Reference: where that instance is (its series, in this study).
  DcmItem* series = nullptr;
  if (d->findOrCreateSequenceItem(DCM_ReferencedSeriesSequence, series, -2).good() &&
      series != nullptr) {
    series->putAndInsertString(DCM_SeriesInstanceUID, src.series_uid.c_str());
    DcmItem* instance = nullptr;
    if (series->findOrCreateSequenceItem(DCM_ReferencedInstanceSequence, instance, -2).good() &&
        instance != nullptr) {
      instance->putAndInsertString(DCM_ReferencedSOPClassUID, src.slices[0].sop_class_uid.c_str());
      instance->putAndInsertString(DCM_ReferencedSOPInstanceUID,
                                   src.slices[0].sop_instance_uid.c_str());
    }
  }
  d->putAndInsertString(DCM_MIMETypeOfEncapsulatedDocument, "model/stl");
  // The value is padded to even length; the length attribute keeps the file's own.
  d->putAndInsertUint32(DCM_EncapsulatedDocumentLength, static_cast<Uint32>(stl->size()));
  if (stl->size() % 2 != 0) stl->push_back('\0');
  d->putAndInsertUint8Array(DCM_EncapsulatedDocument, reinterpret_cast<const Uint8*>(stl->data()),
                            static_cast<unsigned long>(stl->size()));
  OFCondition c = ff.saveFile(out.c_str(), EXS_LittleEndianExplicit);
  if (c.bad()) return DcmError(out.string(), c);
  return absl::OkStatus();
}

absl::Status Check(const OFCondition& c, const std::string& what) {
  return c.good() ? absl::OkStatus() : DcmError(what, c);
}

}  // namespace

std::string NewDicomUid() {
  std::random_device rd;
  unsigned __int128 v = 0;
  for (int i = 0; i < 4; ++i) v = (v << 32) | static_cast<uint32_t>(rd());
  // RFC 4122 version 4, variant 1.
  v &= ~(static_cast<unsigned __int128>(0xF) << 76);
  v |= static_cast<unsigned __int128>(0x4) << 76;
  v &= ~(static_cast<unsigned __int128>(0x3) << 62);
  v |= static_cast<unsigned __int128>(0x2) << 62;
  std::string digits;
  do {
    digits.push_back(static_cast<char>('0' + static_cast<int>(v % 10)));
    v /= 10;
  } while (v != 0);
  std::reverse(digits.begin(), digits.end());
  return "2.25." + digits;
}

absl::StatusOr<DicomExportResult> WriteDicomResults(const DicomExportOptions& o) {
  if (o.labels == nullptr) return absl::InvalidArgumentError("WriteDicomResults: no labels");
  auto src_or = ReadSource(o.source_dir, o.series_instance_uid);
  if (!src_or.ok()) return src_or.status();
  const SourceSeries& src = *src_or;
  const Volume& labels = *o.labels;
  const std::string where = o.source_dir.string();
  if (labels.type != VoxelType::kUInt8) {
    return absl::InvalidArgumentError("label map: expected uint8 region indices");
  }
  if (labels.dims[0] != src.columns || labels.dims[1] != src.rows ||
      labels.dims[2] != static_cast<int64_t>(src.slices.size())) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "label map %dx%dx%d does not match the source series %s (%d columns x %d rows x %d "
        "slices)",
        labels.dims[0], labels.dims[1], labels.dims[2], where, src.columns, src.rows,
        src.slices.size()));
  }
  if ((labels.direction.col(0) - src.row).norm() > 1e-3 ||
      (labels.direction.col(1) - src.col).norm() > 1e-3) {
    return absl::InvalidArgumentError(
        absl::StrCat("label map orientation differs from ImageOrientationPatient of ", where));
  }
  // Source slice -> label slice by position (not by file order).
  std::vector<int64_t> label_slice(src.slices.size());
  const Eigen::Affine3d to_index = labels.IndexToPhysical().inverse();
  for (size_t n = 0; n < src.slices.size(); ++n) {
    const Eigen::Vector3d ijk = to_index * src.slices[n].position;
    const int64_t k = std::llround(ijk.z());
    if (std::abs(ijk.z() - static_cast<double>(k)) > 0.05 || k < 0 || k >= labels.dims[2] ||
        std::abs(ijk.x()) > 0.05 || std::abs(ijk.y()) > 0.05) {
      return absl::InvalidArgumentError(
          absl::StrCat(src.slices[n].file.string(), ": ImagePositionPatient ",
                       src.slices[n].position_text, " is not on a slice of the label map"));
    }
    label_slice[n] = k;
  }
  const size_t frame_pixels = static_cast<size_t>(src.rows * src.columns);
  const uint8_t* lab = labels.data<uint8_t>();
  int max_label = -1;
  std::vector<int64_t> count(256, 0);
  for (int64_t i = 0; i < labels.voxel_count(); ++i) ++count[lab[i]];
  for (int v = 0; v < 256; ++v) {
    if (count[v] > 0) max_label = v;
  }
  if (max_label >= 255) return absl::InvalidArgumentError("label map: label 255 or above");

  std::error_code ec;
  fs::create_directories(o.out_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat(o.out_dir.string(), ": ", ec.message()));
  DicomExportResult result;
  result.study_instance_uid = src.study_uid;

  // The segmentation.
  DcmSegmentation* raw = nullptr;
  IODGeneralEquipmentModule::EquipmentInfo equipment("Decima", "decima-server", "1", "1.0");
  ContentIdentificationMacro content("1", "DECIMA_SEG", "Decima level-set regions", "Decima");
  if (OFCondition c = DcmSegmentation::createBinarySegmentation(
          raw, static_cast<Uint16>(src.rows), static_cast<Uint16>(src.columns), equipment, content);
      c.bad()) {
    return DcmError("creating the segmentation", c);
  }
  std::unique_ptr<DcmSegmentation> seg(raw);
  // A source that left out type 2 attributes of the Patient and General Study modules (allowed
  // to be empty, not absent), or the Frame of Reference, still gets a valid SEG: they are
  // imported empty, and the frame of reference gets a new UID (the SEG's frames are placed by
  // the source's positions and reference the source instances).
  DcmDataset source_header(*src.first->getDataset());
  for (const DcmTagKey& tag :
       {DCM_PatientName, DCM_PatientID, DCM_PatientBirthDate, DCM_PatientSex, DCM_StudyDate,
        DCM_StudyTime, DCM_ReferringPhysicianName, DCM_StudyID, DCM_AccessionNumber}) {
    if (!source_header.tagExists(tag)) source_header.insertEmptyElement(tag);
  }
  if (!source_header.tagExistsWithValue(DCM_FrameOfReferenceUID)) {
    source_header.putAndInsertString(DCM_FrameOfReferenceUID, NewDicomUid().c_str());
  }
  if (auto st = Check(seg->importFromSourceImage(source_header, OFTrue),
                      "importing patient/study from " + where);
      !st.ok()) {
    return st;
  }
  // A new series in the source's study, with UIDs from the 2.25 arc.
  if (auto st = Check(seg->getSeries().setSeriesInstanceUID(NewDicomUid().c_str()), "series uid");
      !st.ok()) {
    return st;
  }
  seg->getSeries().setSeriesNumber("9001");
  seg->getSeries().setSeriesDescription("Decima segmentation");
  seg->getSOPCommon().setSOPInstanceUID(NewDicomUid().c_str());

  FGPixelMeasures pixel_measures;
  pixel_measures.setPixelSpacing(src.pixel_spacing_text.c_str());
  const double thickness =
      src.slices.size() > 1 ? (src.slices.back().along_normal - src.slices.front().along_normal) /
                                  static_cast<double>(src.slices.size() - 1)
                            : 1.0;
  pixel_measures.setSliceThickness(src.slice_thickness_text.empty()
                                       ? absl::StrFormat("%.6g", thickness).c_str()
                                       : src.slice_thickness_text.c_str());
  pixel_measures.setSpacingBetweenSlices(absl::StrFormat("%.6g", thickness).c_str());
  if (auto st = Check(seg->addForAllFrames(pixel_measures), "pixel measures"); !st.ok()) return st;
  std::vector<std::string> iop = absl::StrSplit(src.orientation_text, '\\');
  std::unique_ptr<FGPlaneOrientationPatient> orientation(
      FGPlaneOrientationPatient::createMinimal(iop[0].c_str(), iop[1].c_str(), iop[2].c_str(),
                                               iop[3].c_str(), iop[4].c_str(), iop[5].c_str()));
  if (!orientation) return absl::InternalError("plane orientation functional group");
  if (auto st = Check(seg->addForAllFrames(*orientation), "plane orientation"); !st.ok()) return st;

  const std::string dimension_uid = NewDicomUid();
  IODMultiframeDimensionModule& dims = seg->getDimensions();
  if (auto st = Check(
          dims.addDimensionIndex(DCM_ReferencedSegmentNumber, dimension_uid.c_str(),
                                 DCM_SegmentIdentificationSequence, "ReferencedSegmentNumber"),
          "dimension index");
      !st.ok()) {
    return st;
  }
  if (auto st = Check(dims.addDimensionIndex(DCM_ImagePositionPatient, dimension_uid.c_str(),
                                             DCM_PlanePositionSequence, "ImagePositionPatient"),
                      "dimension index");
      !st.ok()) {
    return st;
  }

  // Segments: every region present in the map that the table keeps in the SEG (air is not a
  // tissue; the space around the patient is what viewers show where no segment is). Category and
  // type from the table (the tissue class by HU for CT, else "Tissue": the level set finds
  // intensity classes, not named anatomy).
  std::vector<Uint16> segment_of_label(256, 0);
  for (int r = 0; r <= max_label; ++r) {
    if (count[r] == 0) continue;
    const RegionInfo* info =
        o.regions != nullptr && static_cast<size_t>(r) < o.regions->regions.size()
            ? &o.regions->regions[r]
            : nullptr;
    if (info != nullptr && !info->in_seg) continue;
    const std::string name = info != nullptr ? info->name : absl::StrCat("region ", r + 1);
    const Code tissue{"85756007", "SCT", "Tissue"};
    const Code& cat = info != nullptr ? info->category : tissue;
    const Code& typ = info != nullptr ? info->type : tissue;
    DcmSegment* segment = nullptr;
    CodeSequenceMacro category(cat.value.c_str(), cat.scheme.c_str(), cat.meaning.c_str());
    CodeSequenceMacro type(typ.value.c_str(), typ.scheme.c_str(), typ.meaning.c_str());
    if (OFCondition c = DcmSegment::create(segment, name.c_str(), category, type,
                                           DcmSegTypes::SAT_AUTOMATIC, "Decima level set");
        c.bad()) {
      return DcmError("segment " + name, c);
    }
    std::unique_ptr<DcmSegment> owned(segment);
    if (info != nullptr) {
      double l = 0, a = 0, b = 0;
      IODCIELabUtil::rgb2DicomLab(l, a, b, info->rgb[0] / 255.0, info->rgb[1] / 255.0,
                                  info->rgb[2] / 255.0);
      auto u16 = [](double v) {
        return static_cast<Uint16>(std::clamp(std::lround(v), 0L, 65535L));
      };
      if (OFCondition c = segment->setRecommendedDisplayCIELabValue(u16(l), u16(a), u16(b));
          c.bad()) {
        return DcmError("colour of segment " + name, c);
      }
    }
    Uint16 number = 0;
    if (OFCondition c = seg->addSegment(segment, number); c.bad()) {
      return DcmError("adding segment " + name, c);
    }
    owned.release();  // the segmentation owns it now
    segment_of_label[r] = number;
    ++result.segments;
  }

  // Frames: per segment, per source slice where the segment is present.
  std::vector<Uint8> frame(frame_pixels);
  for (int r = 0; r <= max_label; ++r) {
    if (segment_of_label[r] == 0) continue;
    for (size_t n = 0; n < src.slices.size(); ++n) {
      const uint8_t* slice = lab + label_slice[n] * static_cast<int64_t>(frame_pixels);
      bool any = false;
      for (size_t p = 0; p < frame_pixels; ++p) {
        frame[p] = slice[p] == r ? 1 : 0;
        any = any || frame[p] != 0;
      }
      if (!any) continue;
      const SourceSlice& s = src.slices[n];
      std::vector<std::string> ipp = absl::StrSplit(s.position_text, '\\');
      std::unique_ptr<FGPlanePosPatient> position(
          FGPlanePosPatient::createMinimal(ipp[0].c_str(), ipp[1].c_str(), ipp[2].c_str()));
      FGFrameContent frame_content;
      frame_content.setDimensionIndexValues(segment_of_label[r], 0);
      frame_content.setDimensionIndexValues(static_cast<Uint32>(n + 1), 1);
      OFVector<ImageSOPInstanceReferenceMacro> derivation_images(1);
      derivation_images[0].setReferencedSOPClassUID(s.sop_class_uid.c_str());
      derivation_images[0].setReferencedSOPInstanceUID(s.sop_instance_uid.c_str());
      std::unique_ptr<FGDerivationImage> derivation(DcmSegmentation::createDerivationImageFG(
          derivation_images, "Segmentation of the source image by Decima"));
      if (!position || !derivation) return absl::InternalError("per-frame functional groups");
      OFVector<FGBase*> per_frame;
      per_frame.push_back(position.get());
      per_frame.push_back(&frame_content);
      per_frame.push_back(derivation.get());
      if (OFCondition c = seg->addFrame(frame.data(), segment_of_label[r], per_frame); c.bad()) {
        return DcmError(absl::StrCat("frame of segment ", segment_of_label[r], " slice ", n + 1),
                        c);
      }
      ++result.frames;
    }
  }

  // ReferencedSeriesSequence: every source instance.
  IODReferences references;
  for (const SourceSlice& s : src.slices) {
    references.add(new IODImageReference(src.patient_id.c_str(), src.study_uid.c_str(),
                                         src.series_uid.c_str(), s.sop_instance_uid.c_str(),
                                         s.sop_class_uid.c_str()));
  }
  if (seg->getCommonInstanceReference().addReferences(references, src.study_uid.c_str()) == 0) {
    return absl::InternalError("ReferencedSeriesSequence: no reference added");
  }

  // A map whose every region is air (a phantom, a synthetic series) has no segment, and a SEG
  // without one is no valid object: none is written; the SC images and the models still are.
  if (result.segments > 0) {
    result.segmentation = o.out_dir / "segmentation.dcm";
    if (OFCondition c = seg->saveFile(result.segmentation.c_str(), EXS_LittleEndianExplicit);
        c.bad()) {
      return DcmError(result.segmentation.string(), c);
    }
  }

  // The renders, one SC series.
  const std::string sc_series = NewDicomUid();
  for (size_t i = 0; i < o.renders.size(); ++i) {
    const fs::path out = o.out_dir / absl::StrCat("sc-", i + 1, ".dcm");
    if (auto st = WriteSecondaryCapture(src, o.renders[i], sc_series, static_cast<int>(i + 1), out);
        !st.ok()) {
      return st;
    }
    result.secondary.push_back(out);
  }

  // The region surfaces, one Encapsulated STL series in the SEG's frame of reference.
  OFString frame_of_reference;
  source_header.findAndGetOFString(DCM_FrameOfReferenceUID, frame_of_reference);
  const std::string model_series = NewDicomUid();
  for (size_t i = 0; i < o.surfaces.size(); ++i) {
    const fs::path out = o.out_dir / absl::StrCat("model-", i + 1, ".dcm");
    if (auto st = WriteEncapsulatedStl(src, frame_of_reference.c_str(), o.surfaces[i],
                                       model_series, static_cast<int>(i + 1), out);
        !st.ok()) {
      return st;
    }
    result.models.push_back(out);
  }
  return result;
}

}  // namespace decima::io
