// The scalar lower CSC pattern of a 3N × 3N symmetric system stored as 3 × 3 blocks (the EFG
// models' K, M̂ and their step systems): shared by EfgModel and EfgMssCoupledModel. Pure.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace somasim::models::meshless {

// From the lower block pattern (column c's blocks are block_row[block_start[c] ..
// block_start[c+1]), sorted rows >= c, N columns): the scalar lower CSC pattern (col_start, 3N + 1
// entries; rows) and per scalar entry its source in the column-major block storage
// (9 × block + r + 3 c).
inline void ScalarLowerPattern(const std::vector<int64_t>& block_start,
                               const std::vector<int32_t>& block_row,
                               std::vector<int32_t>* col_start, std::vector<int32_t>* rows,
                               std::vector<int64_t>* source) {
  const auto n = static_cast<int32_t>(block_start.size()) - 1;
  col_start->assign(3 * size_t(n) + 1, 0);
  rows->clear();
  source->clear();
  for (int32_t c = 0; c < n; ++c) {
    const int64_t begin = block_start[size_t(c)], end = block_start[size_t(c) + 1];
    for (int cc = 0; cc < 3; ++cc) {
      for (int64_t slot = begin; slot < end; ++slot) {
        const int32_t row = block_row[size_t(slot)];
        for (int r = row == c ? cc : 0; r < 3; ++r) {
          rows->push_back(3 * row + r);
          source->push_back(9 * slot + r + 3 * cc);
        }
      }
      (*col_start)[3 * size_t(c) + size_t(cc) + 1] = static_cast<int32_t>(rows->size());
    }
  }
}

}  // namespace somasim::models::meshless
