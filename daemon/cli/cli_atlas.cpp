#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"

#include <iostream>
#include <memory>

namespace slicestation::daemon {

CommandRunner addAtlasCommands(CLI::App& app) {
    auto* atlas = app.add_subcommand("atlas", "Prepare atlas stacks and match sections to them");
    atlas->require_subcommand(1);

    auto sliceRq = std::make_shared<AtlasSliceRequest>();
    auto* slice = atlas->add_subcommand(
        "slice", "Cut a 3-D annotation volume (or the built-in atlas) for a cutting plan");
    slice->add_flag("--builtin", sliceRq->builtin, "Slice the built-in procedural atlas");
    slice->add_option("--volume", sliceRq->volume, "Annotation volume (NRRD, uint16/uint32 ids)");
    slice->add_option("--ontology", sliceRq->ontology, "Allen structure tree CSV");
    slice->add_option("--axes", sliceRq->axes, "Axis convention of the volume: allen|quicknii");
    slice->add_option("--plane", sliceRq->plane, "coronal|sagittal|horizontal");
    slice->add_option("--interval-um", sliceRq->intervalUm, "Distance between slices")
        ->check(finiteRange(kMinIntervalUm, kMaxIntervalUm));
    slice->add_option("--first-um", sliceRq->firstUm, "Position of the first slice")
        ->check(finiteRange(-kMaxPositionUm, kMaxPositionUm));
    slice
        ->add_option("--tilt-lr-deg", sliceRq->tiltLrDeg,
                     "Tilt of the normal toward the image columns (coronal: left-right)")
        ->check(finiteRange(-kMaxTiltDeg, kMaxTiltDeg));
    slice
        ->add_option("--tilt-dv-deg", sliceRq->tiltDvDeg,
                     "Tilt of the normal toward the image rows (coronal: dorsal-ventral)")
        ->check(finiteRange(-kMaxTiltDeg, kMaxTiltDeg));
    slice->add_option("--um-per-px", sliceRq->umPerPx, "Pixel size of the slices")
        ->check(finiteRange(kMinSliceUmPerPx, kMaxUmPerPx));
    slice->add_option("--regions", sliceRq->regions, "major (paper's 20 + tracts, ventricles)|all");
    slice->add_option("--template", sliceRq->templateVolume,
                      "Intensity volume of the same space (NRRD, e.g. the Allen average "
                      "template, axes as --axes): cut beside every slice as its atlas intensity");
    slice->add_option("--output", sliceRq->output, "Stack directory")->required();

    auto matchRq = std::make_shared<AtlasMatchRequest>();
    auto expected = std::make_shared<int>(-1);
    auto* match = atlas->add_subcommand("match", "Find the stack slice a section image came from");
    match->add_option("--stack", matchRq->stack, "Stack directory (or its manifest.json)")
        ->required();
    match->add_option("--image", matchRq->image, "Section image (PNG or TIFF)")->required();
    match->add_option("--expected-index", *expected, "Slice the cutting plan expects")
        ->check(CLI::Range(0, pipeline::kMaxStackSlices - 1));
    match->add_option("--window", matchRq->window, "Slices either side of the expected one")
        ->check(CLI::Range(0, pipeline::kMaxStackSlices));
    match->add_option("--image-um-per-px", matchRq->imageUmPerPx, "Section pixel size")
        ->check(finiteRange(kMinUmPerPx, kMaxUmPerPx));
    match->add_option("--output", matchRq->output, "MATCH.json")->required();

    return [=]() -> int {
        if (!*atlas)
            return -1;
        if (*slice) {
            // The progress line is erased (its object ends) before the result is printed.
            auto r = [&] {
                Progress progress("atlas slice");
                AtlasSliceRequest rq = *sliceRq;
                if (progress.enabled())
                    rq.progress = [&progress, last = std::string()](const std::string& phase,
                                                                    int done, int total) mutable {
                        if (phase != last)
                            progress.phase(last = phase, total);
                        progress.advance(done);
                    };
                return runAtlasSlice(rq);
            }();
            if (!r)
                return reportError("atlas slice", r.error());
            std::cout << "wrote " << (*r)["slices"].get<int>() << " slices ("
                      << (*r)["first_position_um"].get<double>() << ".."
                      << (*r)["last_position_um"].get<double>() << " um) to "
                      << sliceRq->output.string() << "\n";
            return 0;
        }
        AtlasMatchRequest rq = *matchRq;
        if (*expected >= 0)
            rq.expectedIndex = *expected;
        core::Result<nlohmann::json> r = [&] {
            Progress progress("atlas match");
            if (progress.enabled())
                rq.progress = [&progress, last = std::string()](const std::string& phase, int done,
                                                                int total) mutable {
                    if (phase != last)
                        progress.phase(last = phase, total);
                    progress.advance(done, total);
                };
            return runAtlasMatch(rq);
        }();
        if (!r)
            return reportError("atlas match", r.error());
        std::cout << "matched " << rq.image.string() << ": slice " << (*r)["index"].get<int>()
                  << " at " << (*r)["position_um"].get<double>() << " um (score "
                  << (*r)["score"].get<double>() << ", "
                  << (*r)["timings_ms"]["total"].get<double>() << " ms)\n";
        return 0;
    };
}

} // namespace slicestation::daemon
