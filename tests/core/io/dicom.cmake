# Tests of the DICOM series reader; included from tests/core/io/CMakeLists.txt. The tests write
# their synthetic series with GDCM, hence the direct link.
decima_test(dicom_test SOURCES dicom_test.cc DEPS decima::dicom decima_testing_dicom LABELS unit)
