#include "slicestation/daemon/station/section_steps.hpp"

#include "slicestation/daemon/service/systemd_notifier.hpp"
#include "slicestation/daemon/station/retry_policy.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"
#include "slicestation/pipeline/frame_image.hpp"
#include "slicestation/pipeline/tile_stitching.hpp"

#include <opencv2/core.hpp>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

/// The readable part of a file name: ASCII letters, digits, '-' and '_' kept, every other byte
/// '_', at most kMaxNamePart bytes. Not injective ("s/1" and "s_1" both give "s_1"): the path
/// adds the journal's ids for that (imagePathFor).
constexpr std::size_t kMaxNamePart = 48;
std::string safeName(const std::string& s) {
    std::string out;
    for (char c : s) {
        if (out.size() == kMaxNamePart)
            break;
        const auto u = static_cast<unsigned char>(c);
        out += (u < 0x80 && (std::isalnum(u) || c == '-' || c == '_')) ? c : '_';
    }
    return out.empty() ? std::string("_") : out;
}

/// Camera-to-stage orientation: camera axes lie along stage axes (a signed permutation, checked
/// by the settings), so turning a frame into the stage frame is a transpose and/or flips.
struct Orientation {
    bool transpose = false, flipX = false, flipY = false;
};
Orientation orientation(const std::array<double, 4>& m) {
    Orientation o;
    double a = m[0], d = m[3];
    if (std::abs(m[0]) < 0.5) { // axes swapped: after a transpose the matrix is [b a; d c]
        o.transpose = true;
        a = m[1];
        d = m[2];
    }
    o.flipX = a < 0;
    o.flipY = d < 0;
    return o;
}
cv::Mat orient(const cv::Mat& m, const Orientation& o) {
    cv::Mat out = m;
    if (o.transpose)
        cv::transpose(out, out);
    if (o.flipX && o.flipY)
        cv::flip(out, out, -1);
    else if (o.flipX)
        cv::flip(out, out, 1);
    else if (o.flipY)
        cv::flip(out, out, 0);
    return out;
}

} // namespace

std::filesystem::path imagePathFor(const RunRecord& run, const SectionRecord& sec, int attempt) {
    char slide[16];
    std::snprintf(slide, sizeof slide, "%02d", sec.slideIndex + 1);
    return std::filesystem::path("runs") / std::to_string(run.id) /
           (std::string(slide) + "-" + safeName(sec.slideName)) /
           (std::to_string(sec.id) + "-" + safeName(sec.name) + "-a" + std::to_string(attempt) +
            ".ome.tif");
}

Step<hw::CameraSettings> SectionSteps::configureCamera() {
    auto c = configureWithRetries(d_.camera, s_.camera, s_.captureTimeout, s_.captureRetries);
    if (!c)
        return Fault{AlertKind::CameraFault, c.error()};
    const bool transposed = orientation(s_.objective.cameraToStage).transpose;
    fieldWUm_ = (transposed ? c->height : c->width) * s_.objective.umPerPx;
    fieldHUm_ = (transposed ? c->width : c->height) * s_.objective.umPerPx;
    return *c;
}

std::optional<Fault> SectionSteps::checkDisk() const {
    if (!d_.freeSpace)
        return std::nullopt;
    auto free = d_.freeSpace(d_.stateDir);
    if (!free)
        return Fault{AlertKind::StorageFault, free.error()};
    if (*free >= s_.minFreeBytes)
        return std::nullopt;
    return Fault{AlertKind::LowDisk,
                 makeError(ErrorCode::IoError, "low disk: " + std::to_string(*free >> 20) +
                                                   " MB free in " + d_.stateDir.string() +
                                                   ", the threshold is " +
                                                   std::to_string(s_.minFreeBytes >> 20) + " MB")};
}

Step<hw::StagePosition> SectionSteps::move(hw::StagePosition target) {
    PhaseTimer t(d_.stats, "move");
    if (!d_.stage.limits().z)
        target.zUm = 0;
    auto r = moveWithRetries(d_.stage, target, s_.moveTimeout, s_.moveRetries);
    if (!r)
        return Fault{AlertKind::StageFault, r.error()};
    if (d_.watchdog)
        d_.watchdog->progress();
    return *r;
}

Step<SectionSteps::Focus> SectionSteps::focus(double xUm, double yUm, double zUm) {
    if (!s_.autofocus || !d_.stage.limits().z)
        return Focus{zUm, false, std::nullopt};
    PhaseTimer t(d_.stats, "focus");
    AutofocusSettings afs;
    afs.rangeUm = s_.focusRangeUm;
    afs.coarseStepUm = s_.focusCoarseStepUm;
    afs.fineStepUm = s_.focusFineStepUm;
    afs.minTissueFraction = s_.minTissueFraction;
    afs.moveTimeout = s_.moveTimeout;
    afs.captureTimeout = s_.captureTimeout;
    afs.moveRetries = s_.moveRetries;
    afs.captureRetries = s_.captureRetries;
    afs.camera = s_.camera;
    FocusFailure failed = FocusFailure::Focus;
    auto af = autofocus(d_.stage, d_.camera, {xUm, yUm, zUm}, afs, &failed);
    // A stage error during the focus sweep is a stage fault like any other, a capture error a
    // camera fault; only the search itself failing is a focus fault.
    if (!af)
        return Fault{failed == FocusFailure::Stage    ? AlertKind::StageFault
                     : failed == FocusFailure::Camera ? AlertKind::CameraFault
                                                      : AlertKind::FocusFault,
                     af.error()};
    if (!af->tissueFound)
        return Focus{zUm, false, std::nullopt};
    return Focus{af->zUm, true, af->score};
}

Step<SectionSteps::Capture>
SectionSteps::capture(const SectionRecord& sec, double z,
                      const std::function<void(const std::string&)>& activity) {
    const Orientation o = orientation(s_.objective.cameraToStage);
    const pipeline::TilePlan plan = pipeline::planTiles(
        {sec.xUm, sec.yUm, z}, sec.widthUm, sec.heightUm, fieldWUm_, fieldHUm_, s_.tileOverlap);
    Capture out;
    out.stage = {sec.xUm, sec.yUm, z};
    std::vector<pipeline::Tile> tiles;
    for (const auto& c : plan.centres) {
        auto at = move({c.xUm, c.yUm, z});
        if (!at)
            return at.fault();
        PhaseTimer t(d_.stats, "capture");
        auto frame = captureWithRetries(d_.camera, s_.captureTimeout, s_.captureRetries, s_.camera);
        if (!frame)
            return Fault{AlertKind::CameraFault, frame.error()};
        if (d_.watchdog)
            d_.watchdog->progress();
        out.meta = frame->metadata;
        if (plan.centres.size() == 1)
            out.stage = *at;
        tiles.push_back({orient(pipeline::frameToMat(*frame), o), *at});
    }
    out.tiles = static_cast<int>(tiles.size());
    if (tiles.size() == 1) {
        out.image = tiles.front().image;
        return out;
    }
    if (activity)
        activity("stitching " + std::to_string(tiles.size()) + " tiles");
    PhaseTimer t(d_.stats, "stitch");
    auto stitched = pipeline::stitchTiles(tiles, s_.objective.umPerPx);
    if (!stitched)
        return Fault{AlertKind::CameraFault, stitched.error()};
    out.image = *stitched;
    return out;
}

std::optional<Fault> SectionSteps::writeImage(const std::filesystem::path& rel,
                                              const Capture& capture, const std::string& name,
                                              const hw::CameraSettings& used, Journal& journal) {
    PhaseTimer t(d_.stats, "write");
    const std::filesystem::path full = d_.stateDir / rel;
    std::error_code ec;
    std::filesystem::create_directories(full.parent_path(), ec);
    if (ec)
        return Fault{AlertKind::StorageFault,
                     makeError(ErrorCode::IoError,
                               "cannot create " + full.parent_path().string() + ": " + ec.message(),
                               ec.value())};
    OmeTiffInfo info;
    info.umPerPx = s_.objective.umPerPx;
    info.stage = capture.stage;
    const bool rgb = used.format == hw::PixelFormat::Rgb8;
    info.channel = rgb ? "brightfield" : "fluorescence";
    info.channelRgba = rgb ? 0xFFFFFFFFu : 0x00FF00FFu; // white; green (docs/images.md)
    info.objective = s_.objective.name;
    info.name = name;
    info.exposureUs = capture.meta.exposureUs;
    info.gain = capture.meta.analogueGain;
    info.acquiredUtc = Journal::nowUtc();
    auto w = writeOmeTiffAtomic(full, capture.image, info);
    if (!w && w.error().sysErrno == EEXIST) {
        // The writer never replaces a file. One no capture refers to was written by a run a
        // crash interrupted before it was journaled: it may go. One a capture refers to is never
        // overwritten.
        auto owner = journal.captureWithImage(rel.string());
        if (!owner)
            return Fault{AlertKind::JournalError, owner.error()};
        if (*owner)
            return Fault{AlertKind::StorageFault,
                         makeError(ErrorCode::IoError,
                                   full.string() + " is the image of capture " +
                                       std::to_string(**owner) + "; it is not overwritten",
                                   EEXIST)};
        std::error_code removeEc;
        std::filesystem::remove(full, removeEc);
        w = writeOmeTiffAtomic(full, capture.image, info);
    }
    if (!w)
        return Fault{w.error().sysErrno == ENOSPC ? AlertKind::LowDisk : AlertKind::StorageFault,
                     w.error()};
    return std::nullopt;
}

} // namespace slicestation::daemon
