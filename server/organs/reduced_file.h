// A reduced model on disk (idl/reduced_model.proto; docs/reduced.md): the metadata (protobuf,
// checksummed) and the model's arrays (raw little-endian float64, each checksummed). Written by
// somasim-reduce; read by whoever builds the organ (the server, somasim-solve), which passes the
// organ's mesh so that a file made for another mesh is refused. Offline I/O: allocates freely.
#pragma once

#include <memory>
#include <stdexcept>
#include <string>

#include "common/mesh/mesh_types.h"
#include "idl/reduced_model.pb.h"
#include "server/models/reduced/kl_model.h"
#include "server/models/reduced/nonlinear_model.h"

namespace somasim::organs {

inline constexpr char kReducedMagic[8] = {'S', 'O', 'M', 'A', 'R', 'E', 'D', '\n'};
inline constexpr uint32_t kReducedFormatVersion = 1;

// Every refusal: names the file and what is wrong (truncated at which byte, which checksum,
// which array's shape, the mesh hashes that differ, ...).
class ReducedFileError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// FNV-1a 64 (16 hex digits) of the mesh's rest positions and tetrahedra as little-endian bytes:
// a reduced model is valid only on the exact mesh it was made from.
std::string MeshHash(const mesh::TetMesh& mesh);

// The file's bytes for `metadata` (its arrays and creep lists are filled here from `data`; the
// rest is the caller's) and `data`.
std::string EncodeReducedModel(reduced::ReducedModelMetadata metadata,
                               const models::reduced::KlModelData& data);
// The same for the nonlinear model (kind "ecsw_nonlinear": its material, Prony terms and arrays
// from `data`).
std::string EncodeReducedModel(reduced::ReducedModelMetadata metadata,
                               const models::reduced::NonlinearModelData& data);
// Writes them to `path`, which must not exist (a reduced model is never overwritten: write a
// new one and point the scene at it). Throws ReducedFileError.
void WriteReducedModel(const std::string& path, const reduced::ReducedModelMetadata& metadata,
                       const models::reduced::KlModelData& data);
void WriteReducedModel(const std::string& path, const reduced::ReducedModelMetadata& metadata,
                       const models::reduced::NonlinearModelData& data);

struct LoadedReducedModel {
  reduced::ReducedModelMetadata metadata;
  // One of the two, by the file's kind.
  std::unique_ptr<models::reduced::KlReducedModel> model;
  std::unique_ptr<models::reduced::NonlinearReducedModel> nonlinear;
  // Whichever it holds (moved out), and its modes and number of modes.
  std::unique_ptr<models::TissueModel> Release();
  const Eigen::MatrixXd& modes() const;
  int32_t num_modes() const { return static_cast<int32_t>(modes().cols()); }
};

// Decodes and checks `bytes` (`name` for the messages): magic, version, checksums, the arrays'
// shapes against each other and the metadata, then the model itself (KlReducedModel::Create's
// checks: finite values, a positive definite reduced stiffness, creep curves; or
// NonlinearReducedModel::Create's: element corners in range, positive weights, the material). With
// `mesh`, also that the file was made for it (node and element counts, MeshHash). Throws
// ReducedFileError.
LoadedReducedModel DecodeReducedModel(const std::string& bytes, const std::string& name,
                                      const mesh::TetMesh* mesh);
LoadedReducedModel LoadReducedModel(const std::string& path, const mesh::TetMesh* mesh);

}  // namespace somasim::organs
