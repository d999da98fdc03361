#include "stage_conformance.hpp"

namespace slicestation::test {
std::vector<StageModel> simStageModels();
std::vector<StageModel> stageModels() {
    return simStageModels();
}
} // namespace slicestation::test
