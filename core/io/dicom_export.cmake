# DICOM results (SEG and Secondary Capture) written with DCMTK (Debian libdcmtk-dev 3.6.7:
# dcmseg, dcmiod, dcmfg), included from core/io/CMakeLists.txt. Reading stays with GDCM
# (dicom.cmake); dcmseg is the maintained writer of Segmentation objects. DCMTK's CMake config
# imports its libraries as DCMTK::<lib>; imported include directories are SYSTEM, so DCMTK's
# headers do not trip -Werror.
if(NOT TARGET DCMTK::dcmseg)
  find_package(DCMTK CONFIG REQUIRED)
endif()
decima_core_module(dicom_export
  SOURCES dicom_export.cc
  DEPS decima::volume absl::status absl::statusor
  PRIVATE_DEPS decima_dicom decima_png DCMTK::dcmseg DCMTK::dcmfg DCMTK::dcmiod DCMTK::dcmdata
               absl::strings absl::str_format)
