// The k largest values of each row, and of each column, of a matrix: the mapper's
// nearest-descriptor search takes them from a block of cosines, both directions of an
// image pair from one product (colmap_ext/mapper/descriptors.py), and so does the
// exact SIFT matcher (colmap_ext/matching.py).
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace colmap_ext {

// Inserts (value, position) into the k largest kept in `best` / `index`, largest first,
// -infinity where fewer were kept; the caller checked value > best[k - 1]. A value equal
// to one already kept goes after it: the earlier position wins ties, as numpy's argmax.
template <typename Index>
inline void insert_largest(float value, Index position, int k, float* best, Index* index) {
  int place = k - 1;
  while (place > 0 && value > best[place - 1]) {
    best[place] = best[place - 1];
    index[place] = index[place - 1];
    --place;
  }
  best[place] = value;
  index[place] = position;
}

// Bits j (of 4) set where values[j] > thresholds[j]: one compare for four entries, as
// nearly every entry of a row of cosines is below what is already kept.
#if defined(__SSE2__)
inline int above(const float* values, const float* thresholds) {
  return _mm_movemask_ps(_mm_cmpgt_ps(_mm_loadu_ps(values), _mm_loadu_ps(thresholds)));
}
inline int above(const float* values, float threshold) {
  return _mm_movemask_ps(_mm_cmpgt_ps(_mm_loadu_ps(values), _mm_set1_ps(threshold)));
}
#else
inline int above(const float* values, const float* thresholds) {
  int bits = 0;
  for (int j = 0; j < 4; ++j) bits |= (values[j] > thresholds[j]) << j;
  return bits;
}
inline int above(const float* values, float threshold) {
  int bits = 0;
  for (int j = 0; j < 4; ++j) bits |= (values[j] > threshold) << j;
  return bits;
}
#endif

// Offers values[begin, end) (positions begin.. ) to the k largest in `best` / `index`.
template <typename Index>
inline void offer_range(const float* values, int64_t begin, int64_t end, int k, float* best,
                        Index* index) {
  int64_t c = begin;
  for (; c + 4 <= end; c += 4) {
    for (int bits = above(values + c, best[k - 1]); bits; bits &= bits - 1) {
      const int64_t at = c + __builtin_ctz(bits);
      if (values[at] > best[k - 1]) insert_largest(values[at], static_cast<Index>(at), k, best, index);
    }
  }
  for (; c < end; ++c)
    if (values[c] > best[k - 1]) insert_largest(values[c], static_cast<Index>(c), k, best, index);
}

// Per row of the row-major (rows x cols) `values`: the columns of its k largest,
// largest first, in `index` / `best` (rows x k); and among the `num_subset` columns
// `subset`, the k_subset largest (positions in `subset`) in `sub_index` / `sub_best`.
// One pass over each row. Places beyond a row's columns (k > cols) hold -infinity at
// column 0, as further rounds of argmax over values already taken would give.
inline void largest_per_row(const float* values, int64_t rows, int64_t cols, int k,
                            const int64_t* subset, int64_t num_subset, int k_subset,
                            int64_t* index, float* best, int64_t* sub_index, float* sub_best) {
  constexpr float lowest = -std::numeric_limits<float>::infinity();
  std::fill(best, best + rows * k, lowest);
  std::fill(index, index + rows * k, 0);
  std::fill(sub_best, sub_best + rows * k_subset, lowest);
  std::fill(sub_index, sub_index + rows * k_subset, 0);
  for (int64_t r = 0; r < rows; ++r) {
    const float* row = values + r * cols;
    if (k > 0) offer_range(row, 0, cols, k, best + r * k, index + r * k);
    float* row_sub_best = sub_best + r * k_subset;
    int64_t* row_sub_index = sub_index + r * k_subset;
    for (int64_t s = 0; k_subset > 0 && s < num_subset; ++s)
      if (row[subset[s]] > row_sub_best[k_subset - 1])
        insert_largest(row[subset[s]], s, k_subset, row_sub_best, row_sub_index);
  }
}

// Per column of the row-major (rows x cols) `values`, whose rows are rows first_row..
// of a larger matrix taken block by block: merges the column's k largest into `index` /
// `best` (cols x k, largest first, rows of the larger matrix), which hold those of the
// blocks before (-infinity at row 0 where none yet). The earlier row wins ties, so the
// result is largest_per_row's on the transposed matrix, without transposing it.
inline void largest_per_column(const float* values, int64_t rows, int64_t cols, int k,
                               int64_t first_row, int64_t* index, float* best) {
  if (k <= 0) return;
  std::vector<float> threshold(cols);  // each column's k-th largest so far, contiguous
  for (int64_t c = 0; c < cols; ++c) threshold[c] = best[c * k + k - 1];
  for (int64_t r = 0; r < rows; ++r) {
    const float* row = values + r * cols;
    const auto offer = [&](int64_t c) {
      if (!(row[c] > threshold[c])) return;
      insert_largest(row[c], first_row + r, k, best + c * k, index + c * k);
      threshold[c] = best[c * k + k - 1];
    };
    int64_t c = 0;
    for (; c + 4 <= cols; c += 4)
      for (int bits = above(row + c, threshold.data() + c); bits; bits &= bits - 1)
        offer(c + __builtin_ctz(bits));
    for (; c < cols; ++c) offer(c);
  }
}

}  // namespace colmap_ext
