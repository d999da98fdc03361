#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/cli/demo_command.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <opencv2/core/utility.hpp>

#include <cmath>
#include <iostream>
#include <memory>
#include <sstream>

namespace slicestation::daemon {

CLI::Validator finiteRange(double min, double max) {
    const std::string text = "[" + plainNumber(min) + ", " + plainNumber(max) + "]";
    return CLI::Validator(
        [min, max, text](std::string& value) -> std::string {
            double v = 0;
            if (!CLI::detail::lexical_cast(value, v) || !std::isfinite(v) || v < min || v > max)
                return "'" + value + "' is not a finite number in " + text;
            return {};
        },
        "FINITE in " + text);
}

int reportError(const char* command, const core::Error& e) {
    std::cerr << "slicectl " << command << ": error: " << e.message << "\n";
    switch (e.code) {
    case core::ErrorCode::Disconnected:
    case core::ErrorCode::Timeout:
    case core::ErrorCode::Alarm:
    case core::ErrorCode::Cancelled:
        return kExitUnreachable;
    default:
        return kExitInput;
    }
}

CommandRunner addRegisterCommand(CLI::App& app) {
    struct Opts {
        RegisterRequest rq;
        std::string points, overlay, warped, atlasTemplate, ontology;
        int slice = -1;
        int threads = 0;
        std::string regionWarp = "on";
    };
    auto o = std::make_shared<Opts>();
    auto* reg = app.add_subcommand("register", "Register one section image to one atlas slice");
    reg->add_option(
           "--atlas", o->rq.atlas,
           "Atlas label image (ids or colour-coded RGB), or a stack directory with --slice")
        ->required();
    reg->add_option("--atlas-template", o->atlasTemplate,
                    "Atlas intensity plane (e.g. the Allen average template cut like the labels; "
                    "one-channel float32, 8- or 16-bit, the labels' size); a stack slice's own "
                    "template is used without it");
    reg->add_option("--ontology", o->ontology,
                    "Allen ontology (structure_tree_safe_2017.csv) naming the ids of a label "
                    "image of every Allen id, so that it is registered as a slice of a stack cut "
                    "--regions all is (not with a stack: its manifest names its regions)");
    reg->add_option("--slice", o->slice, "Slice index when --atlas is a stack directory")
        ->check(CLI::Range(0, pipeline::kMaxStackSlices - 1));
    reg->add_option("--image", o->rq.image, "Section image (PNG or TIFF)")->required();
    reg->add_option("--points", o->points, "CSV with header x,y: section pixels to map");
    reg->add_option("--output", o->rq.output, "Result JSON")->required();
    reg->add_option("--overlay", o->overlay, "Overlay PNG: section with atlas outlines");
    reg->add_option("--warped-labels", o->warped, "Atlas labels in the section frame (TIFF)");
    reg->add_option("--image-um-per-px", o->rq.imageUmPerPx, "Section pixel size (prior on scale)")
        ->check(finiteRange(kMinUmPerPx, kMaxUmPerPx));
    reg->add_option("--atlas-um-per-px", o->rq.atlasUmPerPx, "Atlas pixel size (prior on scale)")
        ->check(finiteRange(kMinUmPerPx, kMaxUmPerPx));
    reg->add_option("--working-size", o->rq.workingMaxSide, "Longer side of the working image")
        ->check(CLI::Range(128, 8192));
    reg->add_option("--max-turn", o->rq.maxTurnDeg,
                    "How far sections are turned on the slide at most, in degrees (the lab's "
                    "mounting rule; 180 = any way)")
        ->check(CLI::Range(0.0, 180.0));
    reg->add_option("--region-warp", o->regionWarp,
                    "With a stack sliced --regions all: fit the map to every region of the "
                    "section's own contrast (on, the default) or not (off)")
        ->check(CLI::IsMember({"on", "off"}));
    reg->add_option("--threads", o->threads,
                    "Threads the registration may use (0: one per core; results are the same "
                    "with any number)")
        ->check(CLI::Range(0, 256));
    return [o, reg]() -> int {
        if (!*reg)
            return -1;
        if (o->threads > 0)
            cv::setNumThreads(o->threads);
        RegisterRequest rq = o->rq;
        rq.regionWarp = o->regionWarp == "on";
        if (!o->points.empty())
            rq.points = o->points;
        if (!o->overlay.empty())
            rq.overlay = o->overlay;
        if (!o->warped.empty())
            rq.warpedLabels = o->warped;
        if (!o->atlasTemplate.empty())
            rq.atlasTemplate = o->atlasTemplate;
        if (auto s = useStackSlice(rq, o->slice); !s)
            return reportError("register", s.error());
        if (!o->ontology.empty())
            if (auto s = useOntology(rq, o->ontology); !s)
                return reportError("register", s.error());
        auto r = [&] {
            Progress progress("register");
            progress.phase("registering " + rq.image.filename().string(),
                           pipeline::kRegistrationSteps);
            if (progress.enabled())
                rq.progress = [&progress](int done, int) { progress.advance(done); };
            return runRegister(rq);
        }();
        if (!r)
            return reportError("register", r.error());
        for (const auto& w : r->value("warnings", nlohmann::json::array()))
            std::cerr << "slicectl register: warning: " << w.get<std::string>() << "\n";
        std::cout << "registered " << rq.image.string() << " -> " << rq.output.string()
                  << " (tissue overlap " << (*r)["quality"]["tissue_overlap"].get<double>() << ", "
                  << (*r)["quality"]["correspondences"].get<int>() << " correspondences, "
                  << (*r)["timings_ms"]["total"].get<double>() << " ms)\n";
        return 0;
    };
}

CommandRunner addDemoCommand(CLI::App& app) {
    auto demo = std::make_shared<DemoRequest>();
    auto* dem = app.add_subcommand(
        "demo", "Generate a section from the built-in atlas, register it, check it");
    dem->add_option("--output-dir", demo->outputDir, "Where to write the files");
    dem->add_option("--seed", demo->seed, "Generator seed");
    dem->add_flag("--damaged", demo->damaged, "Tear the generated section");
    return [demo, dem]() -> int {
        if (!*dem)
            return -1;
        auto r = runDemo(*demo);
        if (!r)
            return reportError("demo", r.error());
        std::cout << r->dump(2) << "\n";
        return 0;
    };
}

} // namespace slicestation::daemon
