#include "tests/testing/dicom_writer.h"

#include <gdcmDataElement.h>
#include <gdcmFile.h>
#include <gdcmItem.h>
#include <gdcmSequenceOfItems.h>
#include <gdcmTag.h>
#include <gdcmWriter.h>

#include <cstdio>
#include <numeric>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "gtest/gtest.h"

namespace decima::testing {
namespace fs = std::filesystem;
namespace {

std::string Decimals(const std::vector<double>& v) {
  std::vector<std::string> parts;
  for (double x : v) {
    char buf[32];
    std::snprintf(buf, sizeof(buf), "%.10g", x);  // DS: at most 16 characters
    parts.push_back(buf);
  }
  return absl::StrJoin(parts, "\\");
}

void PutText(gdcm::DataSet& ds, uint16_t group, uint16_t element, gdcm::VR vr, std::string v) {
  if (v.size() % 2) v.push_back(vr == gdcm::VR::UI ? '\0' : ' ');
  gdcm::DataElement de(gdcm::Tag(group, element));
  de.SetVR(vr);
  de.SetByteValue(v.data(), static_cast<uint32_t>(v.size()));
  ds.Insert(de);
}

void PutUs(gdcm::DataSet& ds, uint16_t group, uint16_t element, uint16_t v) {
  gdcm::DataElement de(gdcm::Tag(group, element));
  de.SetVR(gdcm::VR::US);
  de.SetByteValue(reinterpret_cast<const char*>(&v), 2);
  ds.Insert(de);
}

template <typename T>
void AppendPixels(const SliceSpec& s, std::vector<char>* out) {
  for (int j = 0; j < s.rows; ++j) {
    for (int i = 0; i < s.columns; ++i) {
      for (int c = 0; c < s.samples_per_pixel; ++c) {
        T v = static_cast<T>(s.value(i, j));
        const char* p = reinterpret_cast<const char*>(&v);
        out->insert(out->end(), p, p + sizeof(T));
      }
    }
  }
}

}  // namespace

void WriteSlice(const fs::path& path, const SliceSpec& s) {
  gdcm::Writer writer;
  gdcm::File& file = writer.GetFile();
  gdcm::DataSet& ds = file.GetDataSet();
  PutText(ds, 0x0008, 0x0016, gdcm::VR::UI, s.sop_class_uid);
  PutText(ds, 0x0008, 0x0018, gdcm::VR::UI, absl::StrCat(s.series_uid, ".", s.instance));
  PutText(ds, 0x0008, 0x0060, gdcm::VR::CS, s.modality);
  PutText(ds, 0x0008, 0x103e, gdcm::VR::LO, s.description);
  if (!s.study_date.empty()) PutText(ds, 0x0008, 0x0020, gdcm::VR::DA, s.study_date);
  if (!s.study_description.empty()) {
    PutText(ds, 0x0008, 0x1030, gdcm::VR::LO, s.study_description);
  }
  if (!s.patient_name.empty()) PutText(ds, 0x0010, 0x0010, gdcm::VR::PN, s.patient_name);
  if (!s.patient_id.empty()) PutText(ds, 0x0010, 0x0020, gdcm::VR::LO, s.patient_id);
  if (s.slice_thickness) PutText(ds, 0x0018, 0x0050, gdcm::VR::DS, Decimals({*s.slice_thickness}));
  PutText(ds, 0x0020, 0x000d, gdcm::VR::UI, "1.2.826.0.1.3680043.9.7777.99");
  PutText(ds, 0x0020, 0x000e, gdcm::VR::UI, s.series_uid);
  PutText(ds, 0x0020, 0x0013, gdcm::VR::IS, absl::StrCat(s.instance));
  PutText(ds, 0x0020, 0x0032, gdcm::VR::DS,
          Decimals({s.position.x(), s.position.y(), s.position.z()}));
  PutText(ds, 0x0020, 0x0037, gdcm::VR::DS, Decimals(s.orientation));
  PutUs(ds, 0x0028, 0x0002, static_cast<uint16_t>(s.samples_per_pixel));
  PutText(ds, 0x0028, 0x0004, gdcm::VR::CS, s.samples_per_pixel == 1 ? "MONOCHROME2" : "RGB");
  if (s.samples_per_pixel > 1) PutUs(ds, 0x0028, 0x0006, 0);
  if (!s.number_of_frames.empty()) PutText(ds, 0x0028, 0x0008, gdcm::VR::IS, s.number_of_frames);
  PutUs(ds, 0x0028, 0x0010, static_cast<uint16_t>(s.rows));
  PutUs(ds, 0x0028, 0x0011, static_cast<uint16_t>(s.columns));
  PutText(ds, 0x0028, 0x0030, gdcm::VR::DS, Decimals(s.pixel_spacing));
  PutUs(ds, 0x0028, 0x0100, static_cast<uint16_t>(s.bits_allocated));
  const int bits_stored = s.bits_stored ? s.bits_stored : s.bits_allocated;
  PutUs(ds, 0x0028, 0x0101, static_cast<uint16_t>(bits_stored));
  PutUs(ds, 0x0028, 0x0102, static_cast<uint16_t>(bits_stored - 1));
  PutUs(ds, 0x0028, 0x0103, static_cast<uint16_t>(s.pixel_representation));
  if (s.intercept) PutText(ds, 0x0028, 0x1052, gdcm::VR::DS, Decimals({*s.intercept}));
  if (s.slope) PutText(ds, 0x0028, 0x1053, gdcm::VR::DS, Decimals({*s.slope}));
  if (s.with_sequence) {
    gdcm::SmartPointer<gdcm::SequenceOfItems> sq = new gdcm::SequenceOfItems;
    sq->SetLengthToUndefined();
    gdcm::Item item;
    item.SetVLToUndefined();
    PutText(item.GetNestedDataSet(), 0x0008, 0x1150, gdcm::VR::UI, "1.2.840.10008.5.1.4.1.1.2");
    PutText(item.GetNestedDataSet(), 0x0008, 0x1155, gdcm::VR::UI, "1.2.3.4.5.6");
    sq->AddItem(item);
    gdcm::DataElement de(gdcm::Tag(0x0008, 0x1140));
    de.SetVR(gdcm::VR::SQ);
    de.SetValue(*sq);
    de.SetVLToUndefined();
    ds.Insert(de);
  }
  std::vector<char> pixels;
  const bool is_signed = s.pixel_representation == 1;
  if (s.bits_allocated == 8) {
    is_signed ? AppendPixels<int8_t>(s, &pixels) : AppendPixels<uint8_t>(s, &pixels);
  } else {
    is_signed ? AppendPixels<int16_t>(s, &pixels) : AppendPixels<uint16_t>(s, &pixels);
  }
  if (pixels.size() % 2) pixels.push_back(0);
  gdcm::DataElement pd(gdcm::Tag(0x7fe0, 0x0010));
  pd.SetVR(s.bits_allocated == 8 ? gdcm::VR::OB : gdcm::VR::OW);
  pd.SetByteValue(pixels.data(), static_cast<uint32_t>(pixels.size()));
  ds.Insert(pd);
  file.GetHeader().SetDataSetTransferSyntax(s.transfer_syntax);
  writer.SetFileName(path.c_str());
  ASSERT_TRUE(writer.Write()) << path;
}

std::vector<fs::path> WriteSeries(const fs::path& dir, const SliceSpec& base,
                                  const std::vector<double>& gaps, std::vector<int> name_order,
                                  const std::string& prefix) {
  const size_t n = gaps.size() + 1;
  if (name_order.empty()) {
    name_order.resize(n);
    std::iota(name_order.begin(), name_order.end(), 0);
  }
  const Eigen::Vector3d row(base.orientation[0], base.orientation[1], base.orientation[2]);
  const Eigen::Vector3d col(base.orientation[3], base.orientation[4], base.orientation[5]);
  const Eigen::Vector3d normal = row.cross(col).normalized();
  std::vector<fs::path> paths;
  double along = 0;
  for (size_t s = 0; s < n; ++s) {
    SliceSpec spec = base;
    spec.position = base.position + along * normal;
    spec.instance = static_cast<int>(s) + 1;
    spec.value = [v = base.value, s](int i, int j) { return v(i, j) + 100.0 * s; };
    char name[32];
    std::snprintf(name, sizeof(name), "%02d.dcm", name_order[s]);
    paths.push_back(dir / (prefix + name));
    WriteSlice(paths.back(), spec);
    if (s + 1 < n) along += gaps[s];
  }
  return paths;
}

}  // namespace decima::testing
