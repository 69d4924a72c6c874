// Small meshes built in code, paths of the real meshes in shared/data/meshes, comparisons, and
// the helpers the format tests share (the error a read throws, text edits), for the tests of
// common/mesh and common/mesh_io.
#pragma once

#include <gtest/gtest.h>

#include <cstdint>
#include <random>
#include <string>
#include <string_view>
#include <utility>

#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/mesh_error.h"
#include "tests/support/temp_files.h"  // MakeTempDir, for the tests that include only this file

namespace somasim::testing {

// A box of nx × ny × nz hexahedra, each split into 6 positively oriented tetrahedra, with the
// boundary triangles (outward) as well. Size [m], origin at 0.
mesh_io::MeshData BoxTets(int nx, int ny, int nz, double sx = 1.0, double sy = 1.0,
                          double sz = 1.0);
// The same box's vertices and outward boundary triangles only (a closed surface).
mesh_io::MeshData BoxSurface(int nx, int ny, int nz);
// An open square patch in the z = 0 plane: (n+1)² vertices, 2n² triangles.
mesh_io::MeshData SquarePatch(int n);
// A regular tetrahedron with edge length `edge` [m].
mesh_io::MeshData RegularTet(double edge = 1.0);

// A copy of `bytes` with `changes` randomly chosen bytes set to random values (the damage loop of
// the readers' "only MeshError comes out" tests). `bytes` must not be empty.
std::string DamageBytes(const std::string& bytes, int changes, std::mt19937* rng);

// Absolute path of shared/data/meshes/<name>.
std::string SharedMesh(const std::string& name);
// Absolute path of tests/data/<name>.
std::string TestData(const std::string& name);
// Whole file as bytes; fails the test (and returns "") when unreadable.
std::string Slurp(const std::string& path);
void WriteBytes(const std::string& path, const std::string& bytes);

// The MeshError that calling `read` throws. When it throws none, fails the test (showing the
// start of `input`, what was read, when given) and returns a placeholder kIo error.
template <typename F>
mesh_io::MeshError ErrorFrom(F&& read, std::string_view input = {}) {
  try {
    std::forward<F>(read)();
  } catch (const mesh_io::MeshError& e) {
    return e;
  }
  ADD_FAILURE() << "no MeshError" << (input.empty() ? "" : " for:\n") << input.substr(0, 400);
  return mesh_io::MeshError(mesh_io::MeshErrorKind::kIo, "", {}, "none");
}

// Whether `part` occurs in `text`.
bool Contains(std::string_view text, std::string_view part);
// `text` with the first occurrence of `from` replaced by `to`; fails the test when absent.
std::string Replace(std::string text, std::string_view from, std::string_view to);
// How many elements of `type` the mesh lists as skipped (0 when none).
int64_t SkippedCount(const mesh_io::MeshData& mesh, std::string_view type);

// Same topology (identical index arrays) and coordinates equal to `tolerance` (absolute, m).
::testing::AssertionResult SameMesh(const mesh_io::MeshData& expected,
                                    const mesh_io::MeshData& actual, double tolerance);
// Same as SameMesh up to a renumbering of vertices: each actual vertex is matched to the
// expected vertex at the same position (within tolerance); elements compared in order.
::testing::AssertionResult SameMeshUpToVertexOrder(const mesh_io::MeshData& expected,
                                                   const mesh_io::MeshData& actual,
                                                   double tolerance);

}  // namespace somasim::testing
