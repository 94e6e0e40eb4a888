// The row-table samples of a group's lanes (PolarFieldMap::sample_rows_near): eight lanes per
// instruction where the processor has AVX-512, lane by lane elsewhere, the same numbers either
// way.
//
// A lane's sample is sample_row_near's: while its radius stays in the cell of its last sample,
// the row is that cell's and u is measured from the cell's edge (Estrin's scheme in u); else the
// cell is found again and the row evaluated by Horner's scheme. The vector kernel does the first
// case for eight lanes at once, with sample_row_near's expressions in its order, and leaves
// every other lane to sample_row_near itself. This file is compiled without multiply-add
// contraction (lib/CMakeLists.txt): GCC's AVX-512 sums and products are plain vector operators,
// which it would otherwise fuse, as it would the scalar ones under -march=native. Products and sums are
// rounded alike in a vector lane and in a scalar register, so a lane's field does not depend on
// the path: tests/unit/test_fast_track.cpp compares the two bit for bit.
//
// Why explicit vectors: GCC does not vectorize the lane loop (the gathered rows and the cell
// test are "control flow in loop" to it, with the function compiled for AVX-512 as well). Each
// lane's row is 8 contiguous doubles (FieldRowTable::Rows, 64 bytes); the kernel loads the
// eight lanes' rows as eight vectors and transposes them (24 shuffles), so that each of the 8
// coefficients is one vector over the lanes.
#include "turnfit/field/field_map.hpp"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define TURNFIT_ROW_LANES_AVX512 1
#include <immintrin.h>
#endif

namespace turnfit {

namespace {

#ifdef TURNFIT_ROW_LANES_AVX512
/// The map's numbers the kernel needs.
struct RowLaneConst {
  const FieldRowTable::Rows* rows;  // the table's rows at (cell 0, j, s): a cell's row is this + cell * stride
  long long stride;                 // ntheta * nslot
  double r_min, dr, inv_dr, inv_dth;
};

/// Lanes [0, m) (m <= 8) of r and cell: the field of each lane whose radius is still in its
/// cell goes to bz, br, bt; returns those lanes as a bit mask (the others are untouched).
__attribute__((target("avx512f"))) unsigned rows8(const RowLaneConst& k, const double* r, const int* cell, int m,
                                                  double* bz, double* br, double* bt) {
  // (The zero-masked forms of the conversion and the unpacks, with every lane on: GCC 12's
  // unmasked ones start from an "undefined" vector that -Wall reports as uninitialized.)
  const __mmask8 all = 0xFF, act = static_cast<__mmask8>(m >= 8 ? 0xFF : (1u << m) - 1);
  alignas(32) int c[8];
  for (int l = 0; l < 8; ++l) c[l] = l < m ? cell[l] : -1;
  const __m512d cd = _mm512_maskz_cvtepi32_pd(all, _mm256_load_si256(reinterpret_cast<const __m256i*>(c)));
  const __m512d rv = _mm512_maskz_loadu_pd(act, r);
  // u = (r - (r_min + cell dr)) / dr, as sample_row_near: the cell's edge, then the offset.
  const __m512d edge = _mm512_add_pd(_mm512_set1_pd(k.r_min), _mm512_mul_pd(cd, _mm512_set1_pd(k.dr)));
  const __m512d u = _mm512_mul_pd(_mm512_sub_pd(rv, edge), _mm512_set1_pd(k.inv_dr));
  const __m512d zero = _mm512_setzero_pd(), one = _mm512_set1_pd(1.0);
  // Ordered compares: a NaN radius is no hit (sample_row_near's u >= 0 && u < 1).
  const __mmask8 hit = static_cast<__mmask8>(_mm512_cmp_pd_mask(cd, zero, _CMP_GE_OQ) &
                                             _mm512_cmp_pd_mask(u, zero, _CMP_GE_OQ) &
                                             _mm512_cmp_pd_mask(u, one, _CMP_LT_OQ) & act);
  if (!hit) return 0;
  // Each lane's row (lanes without a hit load cell 0's, which is never stored).
  __m512d R[8];
  for (int l = 0; l < 8; ++l) {
    const long long cl = (hit >> l) & 1 ? c[l] : 0;
    R[l] = _mm512_loadu_pd(&k.rows[cl * k.stride].row[0]);
  }
  // Transpose: C[q] = coefficient q of lanes 0..7 (q = 0..3 the row, 4..7 the v-derivative's).
  __m512d t[8];
  for (int p = 0; p < 4; ++p) {
    t[2 * p] = _mm512_maskz_unpacklo_pd(all, R[2 * p], R[2 * p + 1]);      // q = 0, 2, 4, 6 of lanes 2p, 2p+1
    t[2 * p + 1] = _mm512_maskz_unpackhi_pd(all, R[2 * p], R[2 * p + 1]);  // q = 1, 3, 5, 7
  }
  const __m512i lo4 = _mm512_setr_epi64(0, 1, 8, 9, 4, 5, 12, 13), hi4 = _mm512_setr_epi64(2, 3, 10, 11, 6, 7, 14, 15);
  // Lanes 0-3 (from t0..t3) and 4-7 (t4..t7): a[0] q = 0, 4; a[1] q = 2, 6; a[2] q = 1, 5; a[3] q = 3, 7.
  __m512d a[4], b[4];
  a[0] = _mm512_permutex2var_pd(t[0], lo4, t[2]);
  a[1] = _mm512_permutex2var_pd(t[0], hi4, t[2]);
  a[2] = _mm512_permutex2var_pd(t[1], lo4, t[3]);
  a[3] = _mm512_permutex2var_pd(t[1], hi4, t[3]);
  b[0] = _mm512_permutex2var_pd(t[4], lo4, t[6]);
  b[1] = _mm512_permutex2var_pd(t[4], hi4, t[6]);
  b[2] = _mm512_permutex2var_pd(t[5], lo4, t[7]);
  b[3] = _mm512_permutex2var_pd(t[5], hi4, t[7]);
  const __m512i lo = _mm512_setr_epi64(0, 1, 2, 3, 8, 9, 10, 11), hi = _mm512_setr_epi64(4, 5, 6, 7, 12, 13, 14, 15);
  const __m512d c0 = _mm512_permutex2var_pd(a[0], lo, b[0]), c4 = _mm512_permutex2var_pd(a[0], hi, b[0]);
  const __m512d c2 = _mm512_permutex2var_pd(a[1], lo, b[1]), c6 = _mm512_permutex2var_pd(a[1], hi, b[1]);
  const __m512d c1 = _mm512_permutex2var_pd(a[2], lo, b[2]), c5 = _mm512_permutex2var_pd(a[2], hi, b[2]);
  const __m512d c3 = _mm512_permutex2var_pd(a[3], lo, b[3]), c7 = _mm512_permutex2var_pd(a[3], hi, b[3]);
  // sample_row_near's expressions, term for term:
  //   bz  = (row0 + row1 u) + u2 (row2 + row3 u)
  //   br  = ((row1 + (2 row2) u) + (3 row3) u2) / dr
  //   bt  = ((drow0 + drow1 u) + u2 (drow2 + drow3 u)) / dtheta
  const __m512d u2 = _mm512_mul_pd(u, u);
  const __m512d vbz = _mm512_add_pd(_mm512_add_pd(c0, _mm512_mul_pd(c1, u)),
                                    _mm512_mul_pd(u2, _mm512_add_pd(c2, _mm512_mul_pd(c3, u))));
  const __m512d two = _mm512_set1_pd(2.0), three = _mm512_set1_pd(3.0);
  const __m512d vbr = _mm512_mul_pd(
      _mm512_add_pd(_mm512_add_pd(c1, _mm512_mul_pd(_mm512_mul_pd(two, c2), u)), _mm512_mul_pd(_mm512_mul_pd(three, c3), u2)),
      _mm512_set1_pd(k.inv_dr));
  const __m512d vbt = _mm512_mul_pd(_mm512_add_pd(_mm512_add_pd(c4, _mm512_mul_pd(c5, u)),
                                                  _mm512_mul_pd(u2, _mm512_add_pd(c6, _mm512_mul_pd(c7, u)))),
                                    _mm512_set1_pd(k.inv_dth));
  _mm512_mask_storeu_pd(bz, hit, vbz);
  _mm512_mask_storeu_pd(br, hit, vbr);
  _mm512_mask_storeu_pd(bt, hit, vbt);
  return hit;
}

bool have_avx512() {
  static const bool yes = __builtin_cpu_supports("avx512f");
  return yes;
}
#endif

}  // namespace

void PolarFieldMap::sample_rows_near(const FieldRowTable& t, int n, const double* r_m, int j, int s, int* cell,
                                     double* bz, double* br, double* bt, unsigned char* good, bool vector) const {
#ifdef TURNFIT_ROW_LANES_AVX512
  const bool kernel = vector && n > 1 && have_avx512();
  const RowLaneConst k{&t.at(0, j, s), static_cast<long long>(t.ntheta) * t.nslot, r_min_, grid_.dr_m(), inv_dr_,
                       inv_dth_};
#else
  (void)vector;
#endif
  // Blocks of eight lanes: the kernel's (bit l - b of done), then the block's others one by one.
  for (int b = 0; b < n; b += 8) {
    const int e = n - b < 8 ? n : b + 8;
    unsigned done = 0;
#ifdef TURNFIT_ROW_LANES_AVX512
    if (kernel) done = rows8(k, r_m + b, cell + b, e - b, bz + b, br + b, bt + b);
#endif
    for (int l = b; l < e; ++l) {
      if ((done >> (l - b)) & 1) continue;
      FieldSample f;
      if (!sample_row_near(t, r_m[l], j, s, cell[l], f)) {
        good[l] = 0;
        f = FieldSample{};
      }
      bz[l] = f.bz_T;
      br[l] = f.dbz_dr_T_m;
      bt[l] = f.dbz_dth_T;
    }
  }
}

}  // namespace turnfit
