// Ceres' log lines kept off a tool's stderr.
#pragma once

namespace turnfit {

/// Ceres logs through glog, and some of its lines (a minimizer giving up after refused steps:
/// an expected outcome, reported by the fit's own result) ignore logging_type = SILENT. A
/// tool's stderr is its own: glog is initialized once and told to print only fatal errors.
/// Call before the first ceres::Solve; thread-safe.
void quiet_ceres_logging();

}  // namespace turnfit
