// A DICOM receiver check's outcome as the receiver stores it (JobStore::PutDicomSeries), with
// the fields the store and handler tests set; its receive key is "<set>@r".
#pragma once

#include <string>

#include "server/store/job_store.h"

namespace decima::server {

inline DicomSeriesRecord Check(const std::string& set, const std::string& series,
                               const std::string& job, const std::string& reason,
                               v1::ReceivedSeries::State state) {
  DicomSeriesRecord r;
  r.receive_key = set + "@r";
  r.instance_set = set;
  r.series_instance_uid = series;
  r.job = job;
  r.reason = reason;
  r.route = "r";
  r.state = state;
  return r;
}

}  // namespace decima::server
