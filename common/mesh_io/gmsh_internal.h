// Internal to the Gmsh reader: helpers its version-specific parts share.
#pragma once

#include <cstdint>
#include <string>
#include <unordered_map>
#include <vector>

namespace somasim::mesh_io::gmsh_internal {

inline std::string Plural(int64_t n, const char* one, const char* many) {
  return std::to_string(n) + " " + (n == 1 ? one : many);
}

// Ids of nodes or elements as the file numbers them, mapped to their 0-based position in file
// order. Files nearly always number 1, 2, 3...: that case needs no hash map.
class IdMap {
 public:
  void Reserve(int64_t n) { where_.reserve(static_cast<size_t>(n)); }
  int64_t size() const { return static_cast<int64_t>(where_.size()); }
  // Records the next item, found at `where` (line or byte offset). Returns the position of an
  // earlier item with the same id, or -1.
  int64_t Add(int64_t id, int64_t where) {
    const int64_t n = size();
    if (sequential_) {
      if (id == n + 1) {
        where_.push_back(where);
        return -1;
      }
      sequential_ = false;
      positions_.reserve(static_cast<size_t>(n) + 1);
      for (int64_t i = 0; i < n; ++i) positions_.emplace(i + 1, i);
    }
    const auto [it, inserted] = positions_.try_emplace(id, n);
    if (!inserted) return it->second;
    where_.push_back(where);
    return -1;
  }
  // Position of the item with this id, or -1.
  int64_t Find(int64_t id) const {
    if (sequential_) return id >= 1 && id <= size() ? id - 1 : -1;
    const auto it = positions_.find(id);
    return it == positions_.end() ? -1 : it->second;
  }
  int64_t where(int64_t position) const { return where_[static_cast<size_t>(position)]; }

 private:
  bool sequential_ = true;  // the ids so far are exactly 1..size()
  std::vector<int64_t> where_;
  std::unordered_map<int64_t, int64_t> positions_;
};

}  // namespace somasim::mesh_io::gmsh_internal
