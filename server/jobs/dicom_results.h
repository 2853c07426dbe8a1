// The job child's DICOM step: when the job's input is a DICOM series (a folder), the results
// are also written as DICOM objects in the source's study (core/io/dicom_export.h):
// segmentation.dcm (SEG, one segment per region of labels.nii.gz) and sc-<n>.dcm (Secondary
// Capture of comparison*.png and diff*.png, in the order the pipeline listed them). They become
// artifacts like the others; sending them to a PACS is dicom_sender.h's business.
#pragma once

#include <filesystem>

#include "absl/status/status.h"
#include "core/pipeline/pipeline.h"

namespace decima::server {

// Appends the DICOM artifacts to `result` for a folder input; does nothing for a volume file or
// when the job's outputs (JobSpec.outputs) left out "labels" (no label map, no SEG); without
// "images" the SEG comes alone.
// Errors name the stage ("dicom: ...") and come from WriteDicomResults or the label map read.
absl::Status AddDicomResults(const pipeline::JobSpec& spec, const std::filesystem::path& out_dir,
                             pipeline::JobResult* result);

}  // namespace decima::server
