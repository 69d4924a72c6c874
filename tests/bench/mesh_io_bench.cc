// Mesh I/O and mesh-analysis benchmarks: how long importing a user's mesh takes.
// Inputs are SOFA's real files in shared/data/meshes, held in memory so disk speed is not
// measured.
#include <benchmark/benchmark.h>

#include <string>

#include "common/mesh/quality.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_io.h"

namespace {

using somasim::mesh_io::FileFormat;

std::string Shared(const std::string& name) {
  return std::string(SOMASIM_SHARED_DIR) + "/data/meshes/" + name;
}

void ReadBench(benchmark::State& state, FileFormat format, const std::string& name,
               somasim::mesh_io::Unit unit) {
  std::string bytes;
  try {
    bytes = somasim::mesh_io::ReadFileBytes(Shared(name));
  } catch (const somasim::mesh_io::MeshError& e) {
    state.SkipWithError(e.what());
    return;
  }
  somasim::mesh_io::ReadOptions options;
  options.unit = unit;
  int64_t elements = 0;
  for (auto _ : state) {
    const somasim::mesh_io::MeshData m =
        somasim::mesh_io::ReadMeshBytes(format, bytes, name, options);
    elements = m.tetrahedra.cols() + m.triangles.cols();
    benchmark::DoNotOptimize(m.vertices.data());
  }
  state.SetBytesProcessed(static_cast<int64_t>(state.iterations()) *
                          static_cast<int64_t>(bytes.size()));
  state.counters["elements"] = static_cast<double>(elements);
}

void BM_ReadVtuAsciiRaptor8418(benchmark::State& state) {
  ReadBench(state, FileFormat::kVtu, "raptorTetra_8418.vtu", somasim::mesh_io::Unit::kMetre);
}
void BM_ReadVtkBinaryLiver5008(benchmark::State& state) {
  ReadBench(state, FileFormat::kVtkLegacy, "liver.vtk", somasim::mesh_io::Unit::kMillimetre);
}
void BM_ReadGmsh1Liver2(benchmark::State& state) {
  ReadBench(state, FileFormat::kGmsh, "liver2.msh", somasim::mesh_io::Unit::kMetre);
}
void BM_ReadObjLiverSmooth(benchmark::State& state) {
  ReadBench(state, FileFormat::kObj, "liver-smooth.obj", somasim::mesh_io::Unit::kCentimetre);
}

void BM_BoundaryAndQualityRaptor8418(benchmark::State& state) {
  somasim::mesh_io::MeshData m;
  try {
    m = somasim::mesh_io::ReadMeshFile(Shared("raptorTetra_8418.vtu"), {});
  } catch (const somasim::mesh_io::MeshError& e) {
    state.SkipWithError(e.what());
    return;
  }
  const somasim::mesh::TetMesh volume{m.vertices, m.tetrahedra};
  for (auto _ : state) {
    const somasim::mesh::SurfaceMesh s = somasim::mesh::ExtractBoundarySurface(volume);
    const somasim::mesh::SurfaceTopology t = somasim::mesh::AnalyseSurfaceTopology(s);
    const somasim::mesh::QualitySummary q = somasim::mesh::SummariseQuality(volume);
    benchmark::DoNotOptimize(t.watertight);
    benchmark::DoNotOptimize(q.min_dihedral_deg);
  }
}

}  // namespace

BENCHMARK(BM_ReadVtuAsciiRaptor8418)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_ReadVtkBinaryLiver5008)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_ReadGmsh1Liver2)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_ReadObjLiverSmooth)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_BoundaryAndQualityRaptor8418)->Unit(benchmark::kMillisecond);
