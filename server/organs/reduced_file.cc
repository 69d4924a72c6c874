#include "server/organs/reduced_file.h"

#include <fcntl.h>
#include <unistd.h>

#include <bit>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <utility>
#include <vector>

#include "common/recording/recording_file.h"

namespace somasim::organs {
namespace {

using models::reduced::CreepCurve;
using models::reduced::KlModelData;

void PutU32(uint32_t v, std::string* out) {
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<char>((v >> (8 * i)) & 0xFFU));
}

uint32_t GetU32(const std::string& in, size_t at) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i) {
    v |= static_cast<uint32_t>(static_cast<uint8_t>(in[at + static_cast<size_t>(i)])) << (8 * i);
  }
  return v;
}

// Doubles as little-endian bytes (this code runs on little-endian x86-64 and ARM: a memcpy).
static_assert(std::endian::native == std::endian::little, "little-endian hosts only");

uint32_t Crc(const char* data, size_t size) {
  return recording::Crc32({reinterpret_cast<const uint8_t*>(data), size});
}

struct Array {
  std::string name;
  const double* data;
  size_t rows, cols;
};

std::string EncodeArrays(reduced::ReducedModelMetadata metadata, const std::vector<Array>& arrays) {
  metadata.clear_arrays();
  std::string body;
  for (const Array& a : arrays) {
    const auto* bytes = reinterpret_cast<const char*>(a.data);
    const size_t size = sizeof(double) * a.rows * a.cols;
    reduced::ArrayInfo* info = metadata.add_arrays();
    info->set_name(a.name);
    info->set_rows(a.rows);
    info->set_cols(a.cols);
    info->set_crc32(Crc(bytes, size));
    if (size > 0) body.append(bytes, size);  // an empty array may have no storage
  }
  std::string meta;
  metadata.SerializeToString(&meta);
  std::string out(kReducedMagic, sizeof kReducedMagic);
  PutU32(kReducedFormatVersion, &out);
  PutU32(static_cast<uint32_t>(meta.size()), &out);
  PutU32(Crc(meta.data(), meta.size()), &out);
  out += meta;
  out += body;
  return out;
}

void WriteBytes(const std::string& path, const std::string& bytes) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
  if (fd < 0) {
    throw ReducedFileError("cannot create " + path + ": " + std::strerror(errno) +
                           (errno == EEXIST ? " (a reduced model is never overwritten)" : ""));
  }
  size_t at = 0;
  while (at < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + at, bytes.size() - at);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      const int error = n < 0 ? errno : EIO;
      ::close(fd);
      ::unlink(path.c_str());
      throw ReducedFileError("cannot write " + path + ": " + std::strerror(error));
    }
    at += static_cast<size_t>(n);
  }
  if (::fsync(fd) != 0 && errno != EINVAL && errno != EROFS) {
    const int error = errno;
    ::close(fd);
    ::unlink(path.c_str());
    throw ReducedFileError("cannot fsync " + path + ": " + std::strerror(error));
  }
  ::close(fd);
}

// That the file was made for `mesh` (counts and MeshHash).
template <typename Fail>
void CheckMesh(const mesh::TetMesh& mesh, const reduced::ReducedModelMetadata& m,
               const Fail& fail) {
  const uint64_t nodes = m.num_nodes();
  if (static_cast<uint64_t>(mesh.vertices.cols()) != nodes ||
      static_cast<uint64_t>(mesh.tetrahedra.cols()) != m.num_tets()) {
    fail("made for a mesh of " + std::to_string(nodes) + " nodes and " +
         std::to_string(m.num_tets()) + " tetrahedra; the organ's has " +
         std::to_string(mesh.vertices.cols()) + " and " + std::to_string(mesh.tetrahedra.cols()));
  }
  const std::string hash = MeshHash(mesh);
  if (hash != m.mesh_hash()) {
    fail("made for another mesh (mesh hash " + m.mesh_hash() + "; the organ's is " + hash + ")");
  }
}

// The index of the array named `name` in m, or -1.
int ArrayIndex(const reduced::ReducedModelMetadata& m, const std::string& name) {
  for (int k = 0; k < m.arrays_size(); ++k) {
    if (m.arrays(k).name() == name) return k;
  }
  return -1;
}

// The nonlinear model from checked arrays (rest, masses and modes' shapes already checked).
template <typename Fail>
std::unique_ptr<models::reduced::NonlinearReducedModel> DecodeNonlinear(
    const reduced::ReducedModelMetadata& m, const std::vector<std::vector<double>>& arrays,
    const Fail& fail) {
  const auto en = static_cast<Eigen::Index>(m.num_nodes());
  const auto ek = static_cast<Eigen::Index>(m.arrays(2).cols());
  const uint64_t elements = m.arrays(3).cols();
  if (m.arrays(3).rows() != 4 || elements < 1) fail("'tets' is not 4 × m (m >= 1)");
  if (m.arrays(4).rows() != elements || m.arrays(4).cols() != 1) fail("'weights' is not m × 1");
  if (m.arrays(5).rows() != elements || m.arrays(5).cols() != 1) fail("'elements' is not m × 1");
  models::reduced::NonlinearModelData data;
  data.rest = Eigen::Map<const mesh::Points>(arrays[0].data(), 3, en);
  data.masses = arrays[1];
  data.modes = Eigen::Map<const Eigen::MatrixXd>(arrays[2].data(), 3 * en, ek);
  data.tets.resize(4, static_cast<Eigen::Index>(elements));
  for (size_t k = 0; k < arrays[3].size(); ++k) {
    const double v = arrays[3][k];
    if (!(v >= 0.0 && v < static_cast<double>(en)) || v != std::floor(v)) {
      fail("'tets' holds " + std::to_string(v) + ", not a node index");
    }
    data.tets.data()[k] = static_cast<int32_t>(v);
  }
  data.weights = arrays[4];
  for (const double v : arrays[5]) {
    if (!(v >= -1.0 && v < 2147483647.0) || v != std::floor(v)) {
      fail("'elements' holds " + std::to_string(v) + ", not an element index");
    }
    if (v >= 0.0) data.elements.push_back(static_cast<int32_t>(v));
  }
  if (!data.elements.empty() && data.elements.size() != elements) {
    fail("'elements' mixes indices and -1");
  }
  const reduced::HyperelasticInfo& h = m.hyperelastic();
  if (h.law() == "reduced_polynomial") {
    data.material.law = models::fem::HyperelasticLaw::kReducedPolynomial;
    if (h.c_size() != 5 || h.d_size() != 3) fail("hyperelastic: c needs 5 values and d 3");
    for (int k = 0; k < 5; ++k) data.material.c[static_cast<size_t>(k)] = h.c(k);
    for (int k = 0; k < 3; ++k) data.material.d[static_cast<size_t>(k)] = h.d(k);
  } else if (h.law() == "st_venant_kirchhoff") {
    data.material.law = models::fem::HyperelasticLaw::kStVenantKirchhoff;
    data.material.lambda = h.lambda_pa();
    data.material.mu = h.mu_pa();
  } else {
    fail("hyperelastic: unknown law '" + h.law() + "'");
  }
  for (const reduced::PronyInfo& p : m.prony()) data.prony.push_back({p.gamma(), p.tau_s()});
  if (ArrayIndex(m, "correction_nodes") == 6) {  // the static correction
    const uint64_t c = m.arrays(6).rows();
    if (m.arrays(6).cols() != 1) fail("'correction_nodes' is not c × 1");
    if (m.arrays(7).rows() != 3 * m.num_nodes() || m.arrays(7).cols() != 3 * c) {
      fail("'corrections' is not 3 num_nodes × 3c (c = " + std::to_string(c) + ")");
    }
    for (const double v : arrays[6]) {
      if (!(v >= 0.0 && v < static_cast<double>(en)) || v != std::floor(v)) {
        fail("'correction_nodes' holds " + std::to_string(v) + ", not a node index");
      }
      data.correction_nodes.push_back(static_cast<int32_t>(v));
    }
    data.corrections = Eigen::Map<const Eigen::MatrixXd>(arrays[7].data(), 3 * en,
                                                         static_cast<Eigen::Index>(3 * c));
    const uint64_t magnitudes = m.arrays(8).rows();
    if (m.arrays(8).cols() != 1) fail("'correction_magnitudes' is not M × 1");
    if (m.arrays(9).rows() != magnitudes || m.arrays(9).cols() != (magnitudes > 0 ? c : 0)) {
      fail("'correction_scales' is not M × c (M = " + std::to_string(magnitudes) + ")");
    }
    data.correction_magnitudes = arrays[8];
    data.correction_scales =
        Eigen::Map<const Eigen::MatrixXd>(arrays[9].data(), static_cast<Eigen::Index>(magnitudes),
                                          static_cast<Eigen::Index>(magnitudes > 0 ? c : 0));
  }
  if (const int k = ArrayIndex(m, "correction_coefficients"); k > 0) {  // after the four
    const uint64_t n = m.arrays(2).cols(), c = m.arrays(6).rows(), magnitudes = m.arrays(8).rows();
    if (m.arrays(k).rows() != n || m.arrays(k).cols() != 4 * magnitudes * c) {
      fail("'correction_coefficients' is not n × 4Mc (n = " + std::to_string(n) +
           ", M = " + std::to_string(magnitudes) + ", c = " + std::to_string(c) + ")");
    }
    data.correction_coefficients = Eigen::Map<const Eigen::MatrixXd>(
        arrays[static_cast<size_t>(k)].data(), ek, static_cast<Eigen::Index>(4 * magnitudes * c));
  }
  if (const int k = ArrayIndex(m, "test_modes"); k > 0) {  // the test basis, last
    if (m.arrays(k).rows() != 3 * m.num_nodes() || m.arrays(k).cols() != m.arrays(2).cols()) {
      fail("'test_modes' is not 3 num_nodes × n like 'modes'");
    }
    data.test_modes =
        Eigen::Map<const Eigen::MatrixXd>(arrays[static_cast<size_t>(k)].data(), 3 * en, ek);
  }
  data.penalty_stiffness = m.penalty_stiffness();
  data.max_local_stiffness = m.max_local_stiffness();
  try {
    return models::reduced::NonlinearReducedModel::Create(std::move(data));
  } catch (const std::invalid_argument& e) {
    fail(e.what());
  }
  return nullptr;
}

}  // namespace

std::string MeshHash(const mesh::TetMesh& mesh) {
  std::string bytes(reinterpret_cast<const char*>(mesh.vertices.data()),
                    sizeof(double) * static_cast<size_t>(mesh.vertices.size()));
  bytes.append(reinterpret_cast<const char*>(mesh.tetrahedra.data()),
               sizeof(int32_t) * static_cast<size_t>(mesh.tetrahedra.size()));
  return recording::TextHash(bytes);
}

std::string EncodeReducedModel(reduced::ReducedModelMetadata metadata, const KlModelData& data) {
  if (metadata.kind().empty()) metadata.set_kind("kl_seed000");
  std::vector<double> creep;
  metadata.clear_creep();
  for (const CreepCurve& c : data.creep) {
    reduced::CreepCurveInfo* info = metadata.add_creep();
    info->set_node(c.node);
    info->set_interval_s(c.interval);
    info->set_samples(c.multiplier.size());
    creep.insert(creep.end(), c.multiplier.begin(), c.multiplier.end());
  }
  metadata.set_creep_radius_m(data.creep_radius);
  metadata.set_penalty_stiffness(data.penalty_stiffness);
  metadata.set_max_local_stiffness(data.max_local_stiffness);
  const std::vector<Array> arrays = {
      {"rest", data.rest.data(), 3, static_cast<size_t>(data.rest.cols())},
      {"masses", data.masses.data(), data.masses.size(), 1},
      {"modes", data.modes.data(), static_cast<size_t>(data.modes.rows()),
       static_cast<size_t>(data.modes.cols())},
      {"stiffness_modes", data.stiffness_modes.data(),
       static_cast<size_t>(data.stiffness_modes.rows()),
       static_cast<size_t>(data.stiffness_modes.cols())},
      {"reduced_stiffness", data.reduced_stiffness.data(),
       static_cast<size_t>(data.reduced_stiffness.rows()),
       static_cast<size_t>(data.reduced_stiffness.cols())},
      {"creep", creep.data(), creep.size(), 1}};
  return EncodeArrays(std::move(metadata), arrays);
}

std::string EncodeReducedModel(reduced::ReducedModelMetadata metadata,
                               const models::reduced::NonlinearModelData& data) {
  if (metadata.kind().empty() || metadata.kind() == "kl_seed000") {
    metadata.set_kind("ecsw_nonlinear");
  }
  metadata.set_penalty_stiffness(data.penalty_stiffness);
  metadata.set_max_local_stiffness(data.max_local_stiffness);
  reduced::HyperelasticInfo* h = metadata.mutable_hyperelastic();
  h->Clear();
  h->set_law(data.material.law == models::fem::HyperelasticLaw::kReducedPolynomial
                 ? "reduced_polynomial"
                 : "st_venant_kirchhoff");
  for (const double c : data.material.c) h->add_c(c);
  for (const double d : data.material.d) h->add_d(d);
  h->set_lambda_pa(data.material.lambda);
  h->set_mu_pa(data.material.mu);
  metadata.clear_prony();
  for (const models::fem::PronyTerm& t : data.prony) {
    reduced::PronyInfo* p = metadata.add_prony();
    p->set_gamma(t.gamma);
    p->set_tau_s(t.tau);
  }
  const std::vector<double> tets(data.tets.data(), data.tets.data() + data.tets.size());
  std::vector<double> elements(data.elements.begin(), data.elements.end());
  if (elements.empty()) elements.assign(data.weights.size(), -1.0);
  std::vector<Array> arrays = {{"rest", data.rest.data(), 3, static_cast<size_t>(data.rest.cols())},
                               {"masses", data.masses.data(), data.masses.size(), 1},
                               {"modes", data.modes.data(), static_cast<size_t>(data.modes.rows()),
                                static_cast<size_t>(data.modes.cols())},
                               {"tets", tets.data(), 4, static_cast<size_t>(data.tets.cols())},
                               {"weights", data.weights.data(), data.weights.size(), 1},
                               {"elements", elements.data(), elements.size(), 1}};
  const std::vector<double> correction_nodes(data.correction_nodes.begin(),
                                             data.correction_nodes.end());
  if (!correction_nodes.empty()) {
    arrays.push_back({"correction_nodes", correction_nodes.data(), correction_nodes.size(), 1});
    arrays.push_back({"corrections", data.corrections.data(),
                      static_cast<size_t>(data.corrections.rows()),
                      static_cast<size_t>(data.corrections.cols())});
    arrays.push_back({"correction_magnitudes", data.correction_magnitudes.data(),
                      data.correction_magnitudes.size(), 1});
    arrays.push_back({"correction_scales", data.correction_scales.data(),
                      static_cast<size_t>(data.correction_scales.rows()),
                      static_cast<size_t>(data.correction_scales.cols())});
    if (data.correction_coefficients.size() > 0) {
      arrays.push_back({"correction_coefficients", data.correction_coefficients.data(),
                        static_cast<size_t>(data.correction_coefficients.rows()),
                        static_cast<size_t>(data.correction_coefficients.cols())});
    }
  }
  if (data.test_modes.size() > 0) {
    arrays.push_back({"test_modes", data.test_modes.data(),
                      static_cast<size_t>(data.test_modes.rows()),
                      static_cast<size_t>(data.test_modes.cols())});
  }
  return EncodeArrays(std::move(metadata), arrays);
}

void WriteReducedModel(const std::string& path, const reduced::ReducedModelMetadata& metadata,
                       const KlModelData& data) {
  WriteBytes(path, EncodeReducedModel(metadata, data));
}

void WriteReducedModel(const std::string& path, const reduced::ReducedModelMetadata& metadata,
                       const models::reduced::NonlinearModelData& data) {
  WriteBytes(path, EncodeReducedModel(metadata, data));
}

LoadedReducedModel DecodeReducedModel(const std::string& bytes, const std::string& name,
                                      const mesh::TetMesh* mesh) {
  const auto fail = [&name](const std::string& what) {
    throw ReducedFileError(name + ": " + what);
  };
  constexpr size_t kPreamble = sizeof kReducedMagic + 12;
  if (bytes.size() < sizeof kReducedMagic ||
      std::memcmp(bytes.data(), kReducedMagic, sizeof kReducedMagic) != 0) {
    fail("not a somasim reduced model (no SOMARED magic)");
  }
  if (bytes.size() < kPreamble) fail("truncated at byte " + std::to_string(bytes.size()));
  const uint32_t version = GetU32(bytes, 8);
  if (version != kReducedFormatVersion) {
    fail("format version " + std::to_string(version) + "; this build reads version " +
         std::to_string(kReducedFormatVersion) +
         (version > kReducedFormatVersion ? " (made by a newer somasim)" : ""));
  }
  const size_t meta_size = GetU32(bytes, 12);
  if (bytes.size() < kPreamble + meta_size) {
    fail("truncated at byte " + std::to_string(bytes.size()) + " (the metadata ends at " +
         std::to_string(kPreamble + meta_size) + ")");
  }
  if (Crc(bytes.data() + kPreamble, meta_size) != GetU32(bytes, 16)) {
    fail("the metadata's checksum does not match");
  }
  LoadedReducedModel out;
  if (!out.metadata.ParseFromArray(bytes.data() + kPreamble, static_cast<int>(meta_size))) {
    fail("the metadata does not parse");
  }
  const reduced::ReducedModelMetadata& m = out.metadata;
  const bool nonlinear = m.kind() == "ecsw_nonlinear";
  if (m.kind() != "kl_seed000" && !nonlinear) {
    fail("unknown reduced model kind '" + m.kind() + "'");
  }
  // The arrays, each checked before it is used.
  size_t at = kPreamble + meta_size;
  std::vector<std::vector<double>> arrays;
  std::vector<std::string> names =
      nonlinear ? std::vector<std::string>{"rest", "masses", "modes", "tets", "weights", "elements"}
                : std::vector<std::string>{
                      "rest", "masses", "modes", "stiffness_modes", "reduced_stiffness", "creep"};
  // A nonlinear model may carry its static correction (four arrays more, then optionally its
  // part in the modes) and then its Petrov–Galerkin test basis (one more), in that order.
  if (nonlinear) {
    const auto named = [&m, &names](const char* array) {
      const auto k = static_cast<int>(names.size());
      return k < m.arrays_size() && m.arrays(k).name() == array;
    };
    if (named("correction_nodes")) {
      names.insert(names.end(), {"correction_nodes", "corrections", "correction_magnitudes",
                                 "correction_scales"});
      if (named("correction_coefficients")) names.push_back("correction_coefficients");
    }
    if (named("test_modes")) names.push_back("test_modes");
  }
  if (m.arrays_size() != static_cast<int>(names.size())) {
    fail("lists " + std::to_string(m.arrays_size()) + " arrays, not " +
         std::to_string(names.size()));
  }
  for (int k = 0; k < m.arrays_size(); ++k) {
    const reduced::ArrayInfo& a = m.arrays(k);
    if (a.name() != names[static_cast<size_t>(k)]) {
      fail("array " + std::to_string(k) + " is '" + a.name() + "', not '" +
           names[static_cast<size_t>(k)] + "'");
    }
    if (a.rows() > (1ULL << 28) || a.cols() > (1ULL << 20) || a.rows() * a.cols() > (1ULL << 31)) {
      fail("array '" + a.name() + "' is implausibly large (" + std::to_string(a.rows()) + " × " +
           std::to_string(a.cols()) + ")");
    }
    const size_t size = sizeof(double) * a.rows() * a.cols();
    if (bytes.size() < at + size) {
      fail("truncated at byte " + std::to_string(bytes.size()) + " (array '" + a.name() +
           "' ends at " + std::to_string(at + size) + ")");
    }
    if (Crc(bytes.data() + at, size) != a.crc32()) {
      fail("array '" + a.name() + "' fails its checksum (at byte " + std::to_string(at) + ")");
    }
    std::vector<double> values(a.rows() * a.cols());
    if (size > 0) std::memcpy(values.data(), bytes.data() + at, size);  // an empty one: no data()
    arrays.push_back(std::move(values));
    at += size;
  }
  if (at != bytes.size()) {
    fail(std::to_string(bytes.size() - at) + " bytes after the last array");
  }
  const auto shape = [&](int k) { return std::make_pair(m.arrays(k).rows(), m.arrays(k).cols()); };
  const uint64_t nodes = m.num_nodes();
  const uint64_t n = m.arrays(2).cols();
  if (shape(0) != std::make_pair<uint64_t, uint64_t>(3, uint64_t{nodes})) {
    fail("'rest' is not 3 × num_nodes (" + std::to_string(nodes) + ")");
  }
  if (shape(1) != std::make_pair<uint64_t, uint64_t>(uint64_t{nodes}, 1)) {
    fail("'masses' is not num_nodes × 1");
  }
  if (shape(2).first != 3 * nodes || n < 1) fail("'modes' is not 3 num_nodes × n");
  if (mesh != nullptr) CheckMesh(*mesh, m, fail);
  if (nonlinear) {
    out.nonlinear = DecodeNonlinear(m, arrays, fail);
    return out;
  }
  if (shape(3) != shape(2)) fail("'stiffness_modes' does not have the modes' shape");
  if (shape(4) != std::make_pair<uint64_t, uint64_t>(uint64_t{n}, uint64_t{n})) {
    fail("'reduced_stiffness' is not n × n (n = " + std::to_string(n) + ")");
  }
  uint64_t samples = 0;
  for (const reduced::CreepCurveInfo& c : m.creep()) samples += c.samples();
  if (shape(5) != std::make_pair<uint64_t, uint64_t>(uint64_t{samples}, 1)) {
    fail("'creep' holds " + std::to_string(m.arrays(5).rows()) + " samples; the curves list " +
         std::to_string(samples));
  }
  KlModelData data;
  const auto en = static_cast<Eigen::Index>(nodes), ek = static_cast<Eigen::Index>(n);
  data.rest = Eigen::Map<const mesh::Points>(arrays[0].data(), 3, en);
  data.masses = arrays[1];
  data.modes = Eigen::Map<const Eigen::MatrixXd>(arrays[2].data(), 3 * en, ek);
  data.stiffness_modes = Eigen::Map<const Eigen::MatrixXd>(arrays[3].data(), 3 * en, ek);
  data.reduced_stiffness = Eigen::Map<const Eigen::MatrixXd>(arrays[4].data(), ek, ek);
  size_t sample = 0;
  for (const reduced::CreepCurveInfo& c : m.creep()) {
    CreepCurve curve;
    curve.node = c.node();
    curve.interval = c.interval_s();
    curve.multiplier.assign(arrays[5].begin() + static_cast<std::ptrdiff_t>(sample),
                            arrays[5].begin() + static_cast<std::ptrdiff_t>(sample + c.samples()));
    sample += c.samples();
    data.creep.push_back(std::move(curve));
  }
  data.creep_radius = m.creep_radius_m();
  data.penalty_stiffness = m.penalty_stiffness();
  data.max_local_stiffness = m.max_local_stiffness();
  try {
    out.model = models::reduced::KlReducedModel::Create(std::move(data));
  } catch (const std::invalid_argument& e) {
    fail(e.what());
  }
  return out;
}

LoadedReducedModel LoadReducedModel(const std::string& path, const mesh::TetMesh* mesh) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ReducedFileError("cannot read " + path + ": " + std::strerror(errno));
  std::ostringstream text;
  text << in.rdbuf();
  return DecodeReducedModel(text.str(), path, mesh);
}

std::unique_ptr<models::TissueModel> LoadedReducedModel::Release() {
  if (model != nullptr) return std::move(model);
  return std::move(nonlinear);
}

const Eigen::MatrixXd& LoadedReducedModel::modes() const {
  return model != nullptr ? model->data().modes : nonlinear->data().modes;
}

}  // namespace somasim::organs
