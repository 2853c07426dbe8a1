// Job results as DICOM objects a PACS stores and its viewers open (DCMTK: dcmseg, dcmiod):
//  - a Segmentation (SEG, 1.2.840.10008.5.1.4.1.1.66.4), BINARY, one segment per region of the
//    label map, on the geometry of the source series: one frame per (segment, source slice)
//    where the segment is present, each frame referencing its source instance (Derivation Image
//    and Frame Content functional groups, Plane Position = the source slice's position) and the
//    source series listed in ReferencedSeriesSequence (OHIF does not overlay a SEG without it);
//  - Secondary Capture images (SC, 1.2.840.10008.5.1.4.1.1.7, RGB) of rendered PNGs, for the
//    many viewers that cannot display a SEG;
//  - Encapsulated STL (1.2.840.10008.5.1.4.1.1.104.3, modality M3D) of the region surfaces, one
//    instance per region named after it, in the source's frame of reference (the surfaces are
//    LPS mm, the patient coordinates DICOM uses), for 3D printing and planning software that
//    takes models from the PACS.
// Both go in the source's study: patient and study attributes are copied from the source
// instances; every new UID (series, instance) is a UUID-derived "2.25." UID (ISO/IEC 9834-8,
// no registered root needed).
// Thread-safety: the functions are independent; DCMTK's dictionary is loaded once, thread-safe.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/volume/regions.h"
#include "core/volume/volume.h"

namespace decima::io {

// A new DICOM UID: "2.25." followed by the decimal value of a random (version 4) UUID.
std::string NewDicomUid();

struct DicomExportOptions {
  // The folder holding the source series (the files the job read) and its uid ("" = the only
  // series in the folder).
  std::filesystem::path source_dir;
  std::string series_instance_uid;
  // Region labels (uint8, 0..K-1, as the job's labels.nii.gz) on the source's grid.
  const Volume* labels = nullptr;
  // The job's region table (core/volume/regions.h): region r present in the map becomes a
  // segment labelled with its name, its category/type codes (Tissue / Soft tissue, Tissue /
  // Bone, Tissue / Tissue) and its colour as RecommendedDisplayCIELabValue; a region the table
  // leaves out of the SEG (in_seg false: air) gets no segment. Without a table (or for a label
  // past its end): "region r+1", Tissue / Tissue, no colour.
  const RegionTable* regions = nullptr;
  // Rendered PNGs (any PNG libpng reads) written as Secondary Capture, one instance each, in one
  // new series, in this order (InstanceNumber 1, 2, ...).
  std::vector<std::filesystem::path> renders;
  // Closed region surfaces (binary STL in LPS mm, as the job's surface-<name>.stl), written as
  // Encapsulated STL, one instance each (DocumentTitle = name), in one new series, in this order.
  struct Surface {
    std::string name;
    std::filesystem::path stl;
  };
  std::vector<Surface> surfaces;
  std::filesystem::path out_dir;  // created if missing
};

struct DicomExportResult {
  std::filesystem::path segmentation;            // out_dir/segmentation.dcm; empty: no segment
  std::vector<std::filesystem::path> secondary;  // out_dir/sc-<n>.dcm
  std::vector<std::filesystem::path> models;     // out_dir/model-<n>.dcm (Encapsulated STL)
  std::string study_instance_uid;                // of the source, shared by all outputs
  int segments = 0;                              // regions present and written as segments
  int frames = 0;                                // SEG frames written
};

// Writes the SEG, the SC and the Encapsulated STL files. InvalidArgument (naming the file and field) when the source
// folder holds no single-frame image series with that uid, slices lack ImagePositionPatient /
// ImageOrientationPatient, the label map's grid differs from the source (dims, orientation, a
// source slice not on a label slice), a label is outside 0..254, or a surface file is no binary
// STL (its size is not 84 + 50 x its triangle count); Internal for DCMTK errors
// (its message included).
absl::StatusOr<DicomExportResult> WriteDicomResults(const DicomExportOptions& options);

}  // namespace decima::io
