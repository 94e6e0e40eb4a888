// Ceres' log lines kept off a tool's stderr (see ceres_logging.hpp).
#include "turnfit/optimize/ceres_logging.hpp"

#include <glog/logging.h>

#include <mutex>

namespace turnfit {

void quiet_ceres_logging() {
  static std::once_flag once;
  std::call_once(once, [] {
    FLAGS_minloglevel = google::GLOG_FATAL;
    FLAGS_logtostderr = true;
    if (!google::IsGoogleLoggingInitialized()) google::InitGoogleLogging("turnfit");
  });
}

}  // namespace turnfit
