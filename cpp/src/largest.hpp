// The k largest values of each row of a matrix: the mapper's nearest-descriptor
// search takes them from a block of cosines (colmap_ext/mapper/descriptors.py).
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>

namespace colmap_ext {

// Inserts (value, column) into the `count` largest of a row found so far, kept
// largest first in `best` / `index` (at most k). A value equal to one already kept
// goes after it: the earlier column wins ties, as with numpy's argmax.
template <typename Index>
inline void keep_largest(float value, Index column, int k, int& count, float* best, Index* index) {
  if (count == k && !(value > best[k - 1])) return;
  int position = count < k ? count : k - 1;
  while (position > 0 && value > best[position - 1]) {
    best[position] = best[position - 1];
    index[position] = index[position - 1];
    --position;
  }
  best[position] = value;
  index[position] = column;
  if (count < k) ++count;
}

// Per row of the row-major (rows x cols) `values`: the columns of its k largest,
// largest first, in `index` / `best` (rows x k); and among the `num_subset` columns
// `subset`, the k_subset largest (positions in `subset`) in `sub_index` / `sub_best`.
// One pass over each row. Places beyond a row's columns (k > cols) hold -infinity at
// column 0, as further rounds of argmax over values already taken would give.
inline void largest_per_row(const float* values, int64_t rows, int64_t cols, int k,
                            const int64_t* subset, int64_t num_subset, int k_subset,
                            int64_t* index, float* best, int64_t* sub_index, float* sub_best) {
  for (int64_t r = 0; r < rows; ++r) {
    const float* row = values + r * cols;
    std::fill(best + r * k, best + (r + 1) * k, -std::numeric_limits<float>::infinity());
    std::fill(index + r * k, index + (r + 1) * k, 0);
    std::fill(sub_best + r * k_subset, sub_best + (r + 1) * k_subset,
              -std::numeric_limits<float>::infinity());
    std::fill(sub_index + r * k_subset, sub_index + (r + 1) * k_subset, 0);
    int count = 0;
    for (int64_t c = 0; k > 0 && c < cols; ++c)
      keep_largest(row[c], c, k, count, best + r * k, index + r * k);
    if (k_subset == 0) continue;
    count = 0;
    for (int64_t s = 0; s < num_subset; ++s)
      keep_largest(row[subset[s]], s, k_subset, count, sub_best + r * k_subset,
                   sub_index + r * k_subset);
  }
}

}  // namespace colmap_ext
