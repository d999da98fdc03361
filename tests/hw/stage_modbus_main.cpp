#include "stage_conformance.hpp"

namespace slicestation::test {
std::vector<StageModel> modbusStageModels();
std::vector<StageModel> stageModels() {
    return modbusStageModels();
}
} // namespace slicestation::test
