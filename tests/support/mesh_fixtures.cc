#include "tests/support/mesh_fixtures.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <sstream>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"

namespace somasim::testing {

mesh_io::MeshData BoxTets(int nx, int ny, int nz, double sx, double sy, double sz) {
  mesh_io::MeshData m;
  const int px = nx + 1, py = ny + 1, pz = nz + 1;
  m.vertices.resize(3, px * py * pz);
  const auto id = [&](int i, int j, int k) { return i + px * (j + py * k); };
  for (int k = 0; k < pz; ++k) {
    for (int j = 0; j < py; ++j) {
      for (int i = 0; i < px; ++i) {
        m.vertices.col(id(i, j, k)) << sx * i / nx, sy * j / ny, sz * k / nz;
      }
    }
  }
  // Kuhn subdivision: six tetrahedra around the diagonal (0,0,0)-(1,1,1) of each cell; the
  // diagonals of neighbouring cells agree, so the mesh is conforming.
  const std::array<std::array<int, 3>, 6> perms = {
      {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}}};
  std::vector<std::array<int32_t, 4>> tets;
  for (int k = 0; k < nz; ++k) {
    for (int j = 0; j < ny; ++j) {
      for (int i = 0; i < nx; ++i) {
        for (const auto& p : perms) {
          std::array<int, 3> c = {i, j, k};
          std::array<int32_t, 4> t;
          t[0] = id(c[0], c[1], c[2]);
          for (int s = 0; s < 3; ++s) {
            ++c[static_cast<size_t>(p[static_cast<size_t>(s)])];
            t[static_cast<size_t>(s) + 1] = id(c[0], c[1], c[2]);
          }
          const double v = mesh::TetSignedVolume(m.vertices.col(t[0]), m.vertices.col(t[1]),
                                                 m.vertices.col(t[2]), m.vertices.col(t[3]));
          if (v < 0) std::swap(t[2], t[3]);
          tets.push_back(t);
        }
      }
    }
  }
  m.tetrahedra.resize(4, static_cast<Eigen::Index>(tets.size()));
  for (size_t t = 0; t < tets.size(); ++t) {
    for (int c = 0; c < 4; ++c) {
      m.tetrahedra(c, static_cast<Eigen::Index>(t)) = tets[t][static_cast<size_t>(c)];
    }
  }
  m.triangles = mesh::ExtractBoundarySurface({m.vertices, m.tetrahedra}).triangles;
  return m;
}

mesh_io::MeshData BoxSurface(int nx, int ny, int nz) {
  mesh_io::MeshData m = BoxTets(nx, ny, nz);
  m.tetrahedra.resize(4, 0);
  std::vector<int32_t> map;
  mesh::SurfaceMesh s = mesh::CompactSurface({m.vertices, m.triangles}, &map);
  m.vertices = s.vertices;
  m.triangles = s.triangles;
  return m;
}

mesh_io::MeshData SquarePatch(int n) {
  mesh_io::MeshData m;
  m.vertices.resize(3, (n + 1) * (n + 1));
  for (int j = 0; j <= n; ++j) {
    for (int i = 0; i <= n; ++i) m.vertices.col(i + (n + 1) * j) << 0.01 * i, 0.01 * j, 0.0;
  }
  m.triangles.resize(3, 2 * n * n);
  int t = 0;
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const int a = i + (n + 1) * j, b = a + 1, c = a + n + 1, d = c + 1;
      m.triangles.col(t++) << a, b, d;
      m.triangles.col(t++) << a, d, c;
    }
  }
  m.tetrahedra.resize(4, 0);
  return m;
}

mesh_io::MeshData RegularTet(double edge) {
  mesh_io::MeshData m;
  m.vertices.resize(3, 4);
  m.vertices.col(0) << 1, 1, 1;
  m.vertices.col(1) << 1, -1, -1;
  m.vertices.col(2) << -1, 1, -1;
  m.vertices.col(3) << -1, -1, 1;
  m.vertices *= edge / (2.0 * std::sqrt(2.0));
  m.tetrahedra.resize(4, 1);
  m.tetrahedra.col(0) << 0, 1, 2, 3;
  if (mesh::TetSignedVolume(m.vertices, m.tetrahedra.col(0)) < 0) {
    std::swap(m.tetrahedra(2, 0), m.tetrahedra(3, 0));
  }
  m.triangles.resize(3, 0);
  return m;
}

std::string DamageBytes(const std::string& bytes, int changes, std::mt19937* rng) {
  std::string damaged = bytes;
  std::uniform_int_distribution<size_t> pos(0, bytes.size() - 1);
  std::uniform_int_distribution<int> value(0, 255);
  for (int k = 0; k < changes; ++k) damaged[pos(*rng)] = static_cast<char>(value(*rng));
  return damaged;
}

std::string SharedMesh(const std::string& name) {
  return std::string(SOMASIM_SHARED_DIR) + "/data/meshes/" + name;
}

std::string TestData(const std::string& name) {
  return std::string(SOMASIM_TEST_DATA_DIR) + "/" + name;
}

std::string Slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  EXPECT_TRUE(in.good()) << "cannot read " << path;
  std::ostringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

void WriteBytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  EXPECT_TRUE(out.good()) << "cannot write " << path;
}

bool Contains(std::string_view text, std::string_view part) {
  return text.find(part) != std::string_view::npos;
}

std::string Replace(std::string text, std::string_view from, std::string_view to) {
  const size_t pos = text.find(from);
  EXPECT_NE(pos, std::string::npos) << "'" << from << "' not found";
  if (pos != std::string::npos) text.replace(pos, from.size(), to);
  return text;
}

int64_t SkippedCount(const mesh_io::MeshData& mesh, std::string_view type) {
  for (const mesh_io::SkippedElements& s : mesh.skipped) {
    if (s.type == type) return s.count;
  }
  return 0;
}

namespace {

::testing::AssertionResult SameElements(const mesh_io::MeshData& e, const mesh_io::MeshData& a,
                                        const std::vector<int32_t>& map) {
  if (e.triangles.cols() != a.triangles.cols()) {
    return ::testing::AssertionFailure()
           << "triangle count " << a.triangles.cols() << ", expected " << e.triangles.cols();
  }
  if (e.tetrahedra.cols() != a.tetrahedra.cols()) {
    return ::testing::AssertionFailure()
           << "tetrahedron count " << a.tetrahedra.cols() << ", expected " << e.tetrahedra.cols();
  }
  for (Eigen::Index i = 0; i < a.triangles.size(); ++i) {
    if (map[static_cast<size_t>(a.triangles.data()[i])] != e.triangles.data()[i]) {
      return ::testing::AssertionFailure() << "triangle #" << i / 3 << " differs";
    }
  }
  for (Eigen::Index i = 0; i < a.tetrahedra.size(); ++i) {
    if (map[static_cast<size_t>(a.tetrahedra.data()[i])] != e.tetrahedra.data()[i]) {
      return ::testing::AssertionFailure() << "tetrahedron #" << i / 4 << " differs";
    }
  }
  return ::testing::AssertionSuccess();
}

}  // namespace

::testing::AssertionResult SameMesh(const mesh_io::MeshData& e, const mesh_io::MeshData& a,
                                    double tolerance) {
  if (e.vertices.cols() != a.vertices.cols()) {
    return ::testing::AssertionFailure()
           << "node count " << a.vertices.cols() << ", expected " << e.vertices.cols();
  }
  for (Eigen::Index i = 0; i < e.vertices.cols(); ++i) {
    const double d = (e.vertices.col(i) - a.vertices.col(i)).cwiseAbs().maxCoeff();
    if (!(d <= tolerance)) {
      return ::testing::AssertionFailure() << "node " << i << " is off by " << d;
    }
  }
  std::vector<int32_t> identity(static_cast<size_t>(a.vertices.cols()));
  for (size_t i = 0; i < identity.size(); ++i) identity[i] = static_cast<int32_t>(i);
  return SameElements(e, a, identity);
}

::testing::AssertionResult SameMeshUpToVertexOrder(const mesh_io::MeshData& e,
                                                   const mesh_io::MeshData& a, double tolerance) {
  // Match by rounding coordinates to the tolerance grid, then check the exact distance.
  std::multimap<std::array<long long, 3>, int32_t> index;
  const double cell = std::max(4 * tolerance, 1e-9);  // [m]; keeps the keys far from overflow
  const auto key = [&](const Eigen::Vector3d& x) {
    return std::array<long long, 3>{std::llround(x[0] / cell), std::llround(x[1] / cell),
                                    std::llround(x[2] / cell)};
  };
  for (Eigen::Index i = 0; i < e.vertices.cols(); ++i) {
    index.emplace(key(e.vertices.col(i)), static_cast<int32_t>(i));
  }
  std::vector<int32_t> map(static_cast<size_t>(a.vertices.cols()), -1);
  for (Eigen::Index i = 0; i < a.vertices.cols(); ++i) {
    const std::array<long long, 3> k = key(a.vertices.col(i));
    for (long long dx = -1; dx <= 1 && map[static_cast<size_t>(i)] < 0; ++dx) {
      for (long long dy = -1; dy <= 1 && map[static_cast<size_t>(i)] < 0; ++dy) {
        for (long long dz = -1; dz <= 1 && map[static_cast<size_t>(i)] < 0; ++dz) {
          auto range = index.equal_range({k[0] + dx, k[1] + dy, k[2] + dz});
          for (auto it = range.first; it != range.second; ++it) {
            if ((e.vertices.col(it->second) - a.vertices.col(i)).cwiseAbs().maxCoeff() <=
                tolerance) {
              map[static_cast<size_t>(i)] = it->second;
              break;
            }
          }
        }
      }
    }
    if (map[static_cast<size_t>(i)] < 0) {
      return ::testing::AssertionFailure()
             << "node " << i << " at (" << a.vertices.col(i).transpose()
             << ") matches no expected node";
    }
  }
  return SameElements(e, a, map);
}

}  // namespace somasim::testing
