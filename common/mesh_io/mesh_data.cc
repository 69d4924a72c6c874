#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

double UnitToMetres(Unit unit) {
  switch (unit) {
    case Unit::kMetre:
      return 1.0;
    case Unit::kCentimetre:
      return 0.01;
    case Unit::kMillimetre:
      return 0.001;
  }
  return 1.0;
}

const char* UnitName(Unit unit) {
  switch (unit) {
    case Unit::kMetre:
      return "m";
    case Unit::kCentimetre:
      return "cm";
    case Unit::kMillimetre:
      return "mm";
  }
  return "m";
}

std::optional<Unit> ParseUnit(std::string_view text) {
  if (text == "m") return Unit::kMetre;
  if (text == "cm") return Unit::kCentimetre;
  if (text == "mm") return Unit::kMillimetre;
  return std::nullopt;
}

void AddSkipped(std::vector<SkippedElements>* skipped, std::string_view type, int64_t count) {
  for (SkippedElements& s : *skipped) {
    if (s.type == type) {
      s.count += count;
      return;
    }
  }
  skipped->push_back({std::string(type), count});
}

}  // namespace somasim::mesh_io
