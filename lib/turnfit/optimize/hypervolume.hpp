// Exact hypervolume of a point set (minimization) w.r.t. a reference point, in any dimension.
#pragma once

#include <vector>

namespace turnfit {

/// The volume of the region dominated by `points` and bounded by `reference` (all objectives
/// minimized): the Lebesgue measure of the union of the boxes [p, reference]. Points not
/// strictly better than the reference in every objective (and points with NaN) contribute
/// nothing; dominated points and duplicates are harmless. Every point must have
/// reference.size() coordinates. Exact in every dimension: 1-D and 2-D by a sort sweep
/// (O(n log n)), 3-D by a sweep in the third objective over a 2-D staircase (O(n^2)), d >= 4
/// by the WFG recursion (While, Bradstreet, Barone 2012: hv = sum of exclusive volumes, the
/// points sorted by their last objective so that each level drops one dimension). Practical
/// up to d = 6 with a few hundred non-dominated points; the cost grows fast beyond.
double hypervolume(const std::vector<std::vector<double>>& points, const std::vector<double>& reference);

/// The same for `n` points stored row by row in `flat` (n * d values, d = reference.size()).
double hypervolume_flat(const std::vector<double>& flat, const std::vector<double>& reference);

}  // namespace turnfit
