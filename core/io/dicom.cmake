# DICOM series reader (decima::dicom), included from core/io/CMakeLists.txt.
#
# GDCM 3.0 from Debian (libgdcm-dev). Its GDCMConfig.cmake works but imports every GDCM command
# line tool as a target and, with libgdcm-tools absent, prints a warning per missing tool on
# each configure; UseGDCM.cmake would also look for VTK. The four libraries we need are found
# directly instead and wrapped in one imported target, GLOBAL so tests can link it too.
if(NOT TARGET decima_gdcm)
  find_path(DECIMA_GDCM_INCLUDE_DIR gdcmImageReader.h PATH_SUFFIXES gdcm-3.0 REQUIRED)
  set(decima_gdcm_libraries)
  foreach(lib gdcmMSFF gdcmDSED gdcmCommon gdcmIOD gdcmDICT)
    find_library(DECIMA_GDCM_${lib}_LIBRARY ${lib} REQUIRED)
    list(APPEND decima_gdcm_libraries ${DECIMA_GDCM_${lib}_LIBRARY})
  endforeach()
  add_library(decima_gdcm INTERFACE IMPORTED GLOBAL)
  # SYSTEM: GDCM's headers are not warning-free under -Wall -Wextra.
  set_target_properties(decima_gdcm PROPERTIES
    INTERFACE_SYSTEM_INCLUDE_DIRECTORIES "${DECIMA_GDCM_INCLUDE_DIR}"
    INTERFACE_INCLUDE_DIRECTORIES "${DECIMA_GDCM_INCLUDE_DIR}"
    INTERFACE_LINK_LIBRARIES "${decima_gdcm_libraries}")
endif()

decima_core_module(dicom
  SOURCES dicom.cc dicom_preflight.cc
  DEPS decima::volume
  PRIVATE_DEPS decima_gdcm absl::strings absl::str_format)
