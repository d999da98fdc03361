// `slicectl count`: cells per atlas region of one registered section (issue 22, docs/cells.md).
//
// The mapping is the one RESULT.json keeps (its "mapping": the affine and the displacement field
// TIFF beside it), so counts come from the very mapping the result shows. Results written before
// the mapping was kept are registered again with the same options (the registration is
// deterministic) and the new affine is checked against the stored one (a note on stderr).
#include "slicestation/core/atomic_file.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/export/section_export.hpp"
#include "slicestation/daemon/station/cell_counts.hpp"
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/preprocess.hpp"

#include <nlohmann/json.hpp>

#include <cmath>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

struct CountRequest {
    std::filesystem::path result, image, output, cells, ontology;
    CellCountOptions options;
    std::string polarity = "auto", method = "log";
    double atlasUmPerPx = 0;
    int workingMaxSide = 1024;
    double maxTurnDeg = 180;
};

core::Result<json> readResult(const std::filesystem::path& p) {
    std::ifstream in(p, std::ios::binary);
    if (!in)
        return makeError(ErrorCode::NotFound, "--result: cannot read " + p.string());
    std::ostringstream text;
    text << in.rdbuf();
    json doc = json::parse(text.str(), nullptr, false);
    if (doc.is_discarded() || !doc.is_object())
        return makeError(ErrorCode::InvalidArgument, "--result " + p.string() + ": not JSON");
    const auto* atlas = doc.contains("atlas") ? &doc["atlas"] : nullptr;
    if (!atlas || !atlas->is_object() || !atlas->contains("path") ||
        !(*atlas)["path"].is_string() || !doc.contains("affine_atlas_from_image") ||
        !doc["affine_atlas_from_image"].is_array() || doc["affine_atlas_from_image"].size() != 2)
        return makeError(ErrorCode::InvalidArgument,
                         "--result " + p.string() +
                             ": not a registration result (atlas.path and "
                             "affine_atlas_from_image are needed)");
    return doc;
}

/// Largest distance (atlas px) between the stored and the re-run affine over the image corners.
core::Result<double> affineDifference(const json& stored, const cv::Matx23d& now, cv::Size size) {
    cv::Matx23d a;
    try {
        for (int r = 0; r < 2; ++r)
            for (int c = 0; c < 3; ++c)
                a(r, c) = stored.at(size_t(r)).at(size_t(c)).get<double>();
    } catch (const json::exception&) {
        return makeError(ErrorCode::InvalidArgument, "affine_atlas_from_image is malformed");
    }
    double worst = 0;
    for (const cv::Point2d p :
         {cv::Point2d(0, 0), cv::Point2d(size.width - 1, 0), cv::Point2d(0, size.height - 1),
          cv::Point2d(size.width - 1, size.height - 1)}) {
        const cv::Point2d u(a(0, 0) * p.x + a(0, 1) * p.y + a(0, 2),
                            a(1, 0) * p.x + a(1, 1) * p.y + a(1, 2));
        const cv::Point2d v(now(0, 0) * p.x + now(0, 1) * p.y + now(0, 2),
                            now(1, 0) * p.x + now(1, 1) * p.y + now(1, 2));
        worst = std::max(worst, cv::norm(u - v));
    }
    return worst;
}

/// The registration that RESULT.json holds, from its saved mapping (the affine and the
/// displacement field beside it): the section's tissue is segmented again as the registration
/// did (pipeline::prepareSection at the mapping's working scale, deterministic), and the damage
/// regions are read from the document. What countCells needs, without registering again.
core::Result<pipeline::Registration>
savedRegistration(const json& doc, const std::filesystem::path& resultDir, const cv::Mat& section) {
    auto mapping = readSavedMapping(doc, resultDir);
    if (!mapping)
        return mapping.error();
    if (mapping->imageSize != section.size())
        return makeError(ErrorCode::InvalidArgument,
                         "the image is " + std::to_string(section.cols) + " x " +
                             std::to_string(section.rows) + " px, the result's mapping is for " +
                             std::to_string(mapping->imageSize.width) + " x " +
                             std::to_string(mapping->imageSize.height));
    const int side = int(std::lround(mapping->workingScale * std::max(section.cols, section.rows)));
    auto prepared = pipeline::prepareSection(section, side);
    if (!prepared)
        return prepared.error();
    if (std::abs(prepared->scale - mapping->workingScale) > 1e-9 * mapping->workingScale)
        return makeError(ErrorCode::Internal, "the tissue could not be segmented at the "
                                              "working scale of the result's mapping");
    pipeline::Registration reg;
    reg.imageSize = mapping->imageSize;
    reg.workingScale = mapping->workingScale;
    reg.atlasFromWorking = mapping->atlasFromWorking;
    if (!mapping->dx.empty())
        reg.warp = pipeline::DisplacementField(mapping->dx, mapping->dy, mapping->cellPx);
    reg.contrast = prepared->contrast;
    reg.workingGrey = prepared->grey;
    reg.workingTissueMask = prepared->tissueMask;
    for (const json& d : doc.value("damage_regions", json::array())) {
        pipeline::DamageRegion region;
        for (const json& p : d.value("polygon", json::array())) {
            if (!p.is_array() || p.size() != 2 || !p[0].is_number() || !p[1].is_number())
                return makeError(ErrorCode::InvalidArgument,
                                 "result: a \"damage_regions\" polygon point is not [x, y]");
            region.polygon.emplace_back(p[0].get<float>(), p[1].get<float>());
        }
        reg.damage.push_back(std::move(region));
    }
    return reg;
}

/// The old way, for results written before the mapping was kept: register the section again to
/// the result's atlas with the same options (the registration is deterministic) and check that
/// the new affine is the stored one over the image corners (1 atlas px at most).
core::Result<pipeline::Registration> registerAgain(const CountRequest& rq, const json& doc,
                                                   const cv::Mat& section, const cv::Mat& labels) {
    pipeline::RegistrationOptions ro;
    // As registerSectionFiles: the pixel sizes are a prior only when both are known.
    if (rq.atlasUmPerPx > 0) {
        ro.imageUmPerPx = rq.options.imageUmPerPx;
        ro.atlasUmPerPx = rq.atlasUmPerPx;
    }
    ro.workingMaxSide = rq.workingMaxSide;
    ro.maxTurnDeg = rq.maxTurnDeg;
    auto reg = pipeline::registerSection(section, labels, ro);
    if (!reg)
        return makeError(reg.error().code,
                         "image " + rq.image.string() + ": " + reg.error().message);
    auto diff = affineDifference(doc["affine_atlas_from_image"], reg->affineAtlasFromImage(),
                                 section.size());
    if (!diff)
        return makeError(diff.error().code, rq.result.string() + ": " + diff.error().message);
    if (*diff > 1.0)
        return makeError(ErrorCode::InvalidArgument,
                         "registering " + rq.image.string() + " again gives a mapping " +
                             plainNumber(*diff, 3) + " atlas px away from " + rq.result.string() +
                             ": pass the options register got (--atlas-um-per-px, "
                             "--working-size, --max-turn)");
    return std::move(*reg);
}

struct MappingUsed {
    pipeline::Registration registration;
    std::string source; ///< "saved" or "registered again"
};

/// The saved mapping when the result holds one, else (a note on stderr) registering again.
core::Result<MappingUsed> mappingOf(const CountRequest& rq, const json& doc, const cv::Mat& section,
                                    const cv::Mat& labels) {
    if (doc.contains("mapping")) {
        auto saved = savedRegistration(doc, rq.result.parent_path(), section);
        if (!saved)
            return makeError(saved.error().code, rq.result.string() + ": " + saved.error().message);
        return MappingUsed{std::move(*saved), "saved"};
    }
    std::cerr << "note: " << rq.result.string()
              << " holds no saved mapping (written before it was kept): registering the section "
                 "again\n";
    auto again = registerAgain(rq, doc, section, labels);
    if (!again)
        return again.error();
    return MappingUsed{std::move(*again), "registered again"};
}

core::Result<json> runCount(CountRequest rq) {
    auto doc = readResult(rq.result);
    if (!doc)
        return doc.error();
    const std::filesystem::path atlasPath = (*doc)["atlas"]["path"].get<std::string>();
    if (rq.image.empty()) {
        if (!(*doc).contains("image") || !(*doc)["image"].contains("path"))
            return makeError(ErrorCode::InvalidArgument, "give --image: the result names none");
        rq.image = (*doc)["image"]["path"].get<std::string>();
    }
    if (rq.options.imageUmPerPx <= 0)
        return makeError(ErrorCode::InvalidArgument,
                         "--image-um-per-px is required: areas are given in mm^2");
    auto ontologyRead = core::readOntologyCsvIfGiven(rq.ontology);
    if (!ontologyRead)
        return ontologyRead.error();
    const core::Ontology& ontology = *ontologyRead;
    auto atlasImage = core::readImage(atlasPath);
    if (!atlasImage)
        return makeError(atlasImage.error().code,
                         "atlas " + atlasPath.string() +
                             " (from the result): " + atlasImage.error().message);
    auto labels = pipeline::labelsFromImage(*atlasImage);
    if (!labels)
        return makeError(labels.error().code,
                         "atlas " + atlasPath.string() + ": " + labels.error().message);
    auto section = core::readImage(rq.image);
    if (!section)
        return makeError(section.error().code,
                         "image " + rq.image.string() + ": " + section.error().message);

    auto mapped = mappingOf(rq, *doc, *section, *labels);
    if (!mapped)
        return mapped.error();
    const pipeline::Registration& reg = mapped->registration;

    rq.options.detector.polarity = rq.polarity == "bright" ? pipeline::CellPolarity::Bright
                                   : rq.polarity == "dark" ? pipeline::CellPolarity::Dark
                                                           : pipeline::CellPolarity::Auto;
    rq.options.detector.method =
        rq.method == "threshold" ? pipeline::CellMethod::Threshold : pipeline::CellMethod::LoG;
    auto counts =
        countSectionCells(*section, reg, *labels, ontology, stackSliceOf(atlasPath), rq.options);
    if (!counts)
        return counts.error();
    if (auto w = core::writeFileAtomically(rq.output, counts->countsCsv); !w)
        return w.error();
    if (!rq.cells.empty())
        if (auto w = core::writeFileAtomically(rq.cells, counts->cellsCsv); !w)
            return w.error();
    std::int64_t counted = 0;
    for (const auto& c : counts->table.cells)
        if (!c.excluded && c.atlasId > 0)
            counted += c.cells;
    return json{{"detections", counts->table.cells.size()},
                {"counted", counted},
                {"excluded_in_damage", counts->table.excludedCells},
                {"regions", counts->table.regions.size()},
                {"diameter_px", counts->diameterPx},
                {"mapping", mapped->source}};
}

} // namespace

CommandRunner addCountCommand(CLI::App& app) {
    auto rq = std::make_shared<CountRequest>();
    auto* cmd = app.add_subcommand(
        "count", "Count cells per atlas region in a registered section (docs/cells.md)");
    cmd->add_option("--result", rq->result, "RESULT.json written by register")->required();
    cmd->add_option("--image", rq->image, "Section image (default: the result's image path)");
    cmd->add_option("--channel", rq->options.detector.channel,
                    "Channel of the cells, in file order (0 = red); default: grey of all")
        ->check(CLI::Range(0, 3));
    cmd->add_option("--output", rq->output, "COUNTS.csv")->required();
    cmd->add_option("--cells", rq->cells, "CELLS.csv: one row per detected cell");
    cmd->add_option("--ontology", rq->ontology,
                    "structure_tree_safe_2017.csv: roll counts up the Allen hierarchy");
    cmd->add_option("--image-um-per-px", rq->options.imageUmPerPx,
                    "Section pixel size (required: areas in mm^2, cell size in px)")
        ->check(finiteRange(kMinUmPerPx, kMaxUmPerPx));
    cmd->add_option("--atlas-um-per-px", rq->atlasUmPerPx,
                    "Atlas pixel size, only if register was given it too")
        ->check(finiteRange(kMinUmPerPx, kMaxUmPerPx));
    cmd->add_option("--working-size", rq->workingMaxSide, "As given to register")
        ->check(CLI::Range(128, 8192));
    cmd->add_option("--max-turn", rq->maxTurnDeg, "As given to register")
        ->check(CLI::Range(0.0, 180.0));
    cmd->add_option("--cell-diameter-um", rq->options.cellDiameterUm,
                    "Typical cell body diameter (default 15)")
        ->check(finiteRange(1, 500));
    cmd->add_option("--min-snr", rq->options.detector.minSnr,
                    "Detection threshold in local noise units (default 4)")
        ->check(finiteRange(0.1, 1000));
    cmd->add_option("--polarity", rq->polarity, "auto, bright (fluorescence) or dark (brightfield)")
        ->check(CLI::IsMember({"auto", "bright", "dark"}));
    cmd->add_option("--method", rq->method, "log (default) or threshold (the paper's rule)")
        ->check(CLI::IsMember({"log", "threshold"}));
    return [rq, cmd]() -> int {
        if (!*cmd)
            return -1;
        auto r = [&] {
            Progress progress("count");
            progress.phase("counting " + rq->result.filename().string());
            return runCount(*rq);
        }();
        if (!r)
            return reportError("count", r.error());
        std::cout << "counted " << (*r)["counted"].get<std::int64_t>() << " cells in "
                  << (*r)["regions"].get<std::size_t>() << " regions -> " << rq->output.string()
                  << " (" << (*r)["excluded_in_damage"].get<std::int64_t>()
                  << " in damage left out; cells " << plainNumber((*r)["diameter_px"], 3)
                  << " px; mapping " << (*r)["mapping"].get<std::string>() << ")\n";
        return 0;
    };
}

} // namespace slicestation::daemon
