// Exact hypervolume: sort sweeps in 1-3 dimensions, the WFG recursion above.
#include "turnfit/optimize/hypervolume.hpp"

#include <algorithm>
#include <limits>
#include <numeric>

#include "turnfit/io/error.hpp"

namespace turnfit {

namespace {

/// Points row by row, d coordinates each.
struct Points {
  size_t d = 0;
  std::vector<double> v;
  size_t size() const { return d ? v.size() / d : 0; }
  const double* row(size_t i) const { return v.data() + i * d; }
};

/// 2-D: sorted by f1 (then f2), each point that lowers the running minimum of f2 adds the strip
/// between its f2 and that minimum, from its f1 to the reference.
double hv2(const Points& p, const double* ref) {
  const size_t n = p.size();
  std::vector<std::pair<double, double>> pts(n);
  for (size_t i = 0; i < n; ++i) pts[i] = {p.row(i)[0], p.row(i)[1]};
  std::sort(pts.begin(), pts.end());
  double area = 0, ymin = ref[1];
  for (const auto& [x, y] : pts) {
    if (y < ymin) {
      area += (ref[0] - x) * (ymin - y);
      ymin = y;
    }
  }
  return area;
}

/// 3-D: points taken in increasing f3; between consecutive f3 levels the dominated slice is
/// the area of the 2-D staircase of the points taken so far (Beume et al. 2009 do the update
/// in O(log n); the O(n) update here is fast enough for populations of thousands).
double hv3(const Points& p, const double* ref) {
  const size_t n = p.size();
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), size_t(0));
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return p.row(a)[2] < p.row(b)[2]; });
  std::vector<std::pair<double, double>> st;  // x increasing, y strictly decreasing
  st.reserve(n);
  std::vector<std::pair<double, double>> tmp;
  tmp.reserve(n);
  double area = 0, vol = 0, zprev = 0;
  for (size_t oi = 0; oi < n; ++oi) {
    const double* q = p.row(order[oi]);
    const double x = q[0], y = q[1], z = q[2];
    if (oi > 0) vol += area * (z - zprev);
    zprev = z;
    // Position of x: everything before has a smaller x.
    auto it = std::lower_bound(st.begin(), st.end(), std::make_pair(x, -std::numeric_limits<double>::infinity()));
    const size_t k = size_t(it - st.begin());
    if (k > 0 && st[k - 1].second <= y) continue;              // dominated by a point left of it
    if (k < st.size() && st[k].first == x && st[k].second <= y) continue;  // same x, lower y
    // Drop the points the new one dominates (x >= its x, y >= its y: contiguous from k).
    size_t e = k;
    while (e < st.size() && st[e].second >= y) ++e;
    st.erase(st.begin() + long(k), st.begin() + long(e));
    st.insert(st.begin() + long(k), {x, y});
    area = 0;
    for (size_t j = 0; j < st.size(); ++j) {
      const double xnext = j + 1 < st.size() ? st[j + 1].first : ref[0];
      area += (xnext - st[j].first) * (ref[1] - st[j].second);
    }
  }
  if (n > 0) vol += area * (ref[2] - zprev);
  return vol;
}

/// Keeps the points no other point weakly dominates (one copy of duplicates), first d dims.
void nondominated(Points& p) {
  const size_t n = p.size(), d = p.d;
  if (n < 2) return;
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), size_t(0));
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    return std::lexicographical_compare(p.row(a), p.row(a) + d, p.row(b), p.row(b) + d);
  });
  std::vector<double> out;
  out.reserve(p.v.size());
  size_t kept = 0;
  for (size_t oi = 0; oi < n; ++oi) {
    const double* a = p.row(order[oi]);
    bool dominated = false;
    // Only a lexicographically smaller point can weakly dominate a.
    for (size_t k = 0; k < kept && !dominated; ++k) {
      const double* b = out.data() + k * d;
      size_t i = 0;
      while (i < d && b[i] <= a[i]) ++i;
      dominated = i == d;
    }
    if (!dominated) {
      out.insert(out.end(), a, a + d);
      ++kept;
    }
  }
  p.v.swap(out);
}

double hv(Points& p, const double* ref);

/// d >= 4: WFG. With the points sorted by the last objective, worst first, every limit set
/// of point k (the points after it, each made no better than point k) shares point k's last
/// objective, so its exclusive volume is a (d-1)-dimensional problem times a height.
double wfg(Points& p, const double* ref) {
  const size_t n = p.size(), d = p.d;
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), size_t(0));
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return p.row(a)[d - 1] > p.row(b)[d - 1]; });
  Points sorted{d, {}};
  sorted.v.reserve(p.v.size());
  for (size_t i : order) sorted.v.insert(sorted.v.end(), p.row(i), p.row(i) + d);
  double total = 0;
  Points limit{d - 1, {}};
  for (size_t k = 0; k < n; ++k) {
    const double* a = sorted.row(k);
    double incl = 1;
    for (size_t i = 0; i + 1 < d; ++i) incl *= ref[i] - a[i];
    limit.v.clear();
    for (size_t j = k + 1; j < n; ++j) {
      const double* b = sorted.row(j);
      for (size_t i = 0; i + 1 < d; ++i) limit.v.push_back(std::max(a[i], b[i]));
    }
    nondominated(limit);
    const double excl = incl - (limit.size() ? hv(limit, ref) : 0.0);
    total += (ref[d - 1] - a[d - 1]) * excl;
  }
  return total;
}

double hv(Points& p, const double* ref) {
  const size_t n = p.size();
  if (n == 0) return 0;
  if (p.d == 1) {
    double best = ref[0];
    for (size_t i = 0; i < n; ++i) best = std::min(best, p.row(i)[0]);
    return ref[0] - best;
  }
  if (n == 1) {
    double v = 1;
    for (size_t i = 0; i < p.d; ++i) v *= ref[i] - p.row(0)[i];
    return v;
  }
  if (p.d == 2) return hv2(p, ref);
  if (p.d == 3) return hv3(p, ref);
  return wfg(p, ref);
}

}  // namespace

double hypervolume_flat(const std::vector<double>& flat, const std::vector<double>& reference) {
  const size_t d = reference.size();
  if (d == 0) throw usage_error("hypervolume: empty reference point");
  if (flat.size() % d != 0) throw usage_error("hypervolume: points do not have the reference's dimension");
  Points p{d, {}};
  p.v.reserve(flat.size());
  for (size_t i = 0; i < flat.size(); i += d) {
    bool inside = true;
    for (size_t k = 0; k < d && inside; ++k) inside = flat[i + k] < reference[k];  // NaN: false
    if (inside) p.v.insert(p.v.end(), flat.begin() + long(i), flat.begin() + long(i + d));
  }
  if (d >= 4) nondominated(p);
  return hv(p, reference.data());
}

double hypervolume(const std::vector<std::vector<double>>& points, const std::vector<double>& reference) {
  std::vector<double> flat;
  flat.reserve(points.size() * reference.size());
  for (const auto& q : points) {
    if (q.size() != reference.size())
      throw usage_error("hypervolume: a point has " + std::to_string(q.size()) + " coordinates, the reference " +
                        std::to_string(reference.size()));
    flat.insert(flat.end(), q.begin(), q.end());
  }
  return hypervolume_flat(flat, reference);
}

}  // namespace turnfit
