#include "slicestation/sim/virtual_slide.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>

namespace slicestation::sim {

using core::ErrorCode;
using core::makeError;

namespace {

core::Error bad(const std::string& field, const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "virtual slide: " + field + ": " + what);
}

/// Median of the one-pixel border of `m`, per channel: the level of its glass.
cv::Scalar borderLevel(const cv::Mat& m) {
    cv::Scalar level;
    std::vector<cv::Mat> ch;
    cv::split(m, ch);
    for (std::size_t c = 0; c < ch.size() && c < 4; ++c) {
        std::vector<double> v;
        const cv::Mat& k = ch[c];
        for (int x = 0; x < k.cols; ++x) {
            v.push_back(k.depth() == CV_16U ? k.at<std::uint16_t>(0, x) : k.at<std::uint8_t>(0, x));
            v.push_back(k.depth() == CV_16U ? k.at<std::uint16_t>(k.rows - 1, x)
                                            : k.at<std::uint8_t>(k.rows - 1, x));
        }
        for (int y = 0; y < k.rows; ++y) {
            v.push_back(k.depth() == CV_16U ? k.at<std::uint16_t>(y, 0) : k.at<std::uint8_t>(y, 0));
            v.push_back(k.depth() == CV_16U ? k.at<std::uint16_t>(y, k.cols - 1)
                                            : k.at<std::uint8_t>(y, k.cols - 1));
        }
        std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
        level[static_cast<int>(c)] = v[v.size() / 2];
    }
    return level;
}

/// Pastes `patch` centred at `centrePx` so that its glass level becomes the slide's: bright
/// tissue on dark glass adds above the glass, dark tissue on bright glass subtracts below it.
void paste(cv::Mat& slide, const cv::Mat& patch, cv::Point2d centrePx, cv::Scalar slideGlass,
           bool darkTissue) {
    const cv::Scalar glass = borderLevel(patch);
    cv::Mat contrast;
    if (darkTissue)
        cv::subtract(glass, patch, contrast); // saturates at 0
    else
        cv::subtract(patch, glass, contrast);
    const cv::Rect r(static_cast<int>(std::lround(centrePx.x - patch.cols / 2.0)),
                     static_cast<int>(std::lround(centrePx.y - patch.rows / 2.0)), patch.cols,
                     patch.rows);
    const cv::Rect clipped = r & cv::Rect(0, 0, slide.cols, slide.rows);
    if (clipped.empty())
        return;
    cv::Mat src =
        contrast(cv::Rect(clipped.x - r.x, clipped.y - r.y, clipped.width, clipped.height));
    cv::Mat dst = slide(clipped);
    cv::Mat base(dst.size(), dst.type(), slideGlass);
    if (darkTissue)
        cv::subtract(base, src, dst);
    else
        cv::add(base, src, dst);
}

} // namespace

core::Result<VirtualSlide> makeVirtualSlide(const VirtualSlideSpec& spec) {
    if (spec.sections.empty())
        return bad("sections", "no sections");
    if (spec.columns < 1)
        return bad("columns", "must be >= 1");
    if (!(spec.umPerPx > 0) || !std::isfinite(spec.umPerPx))
        return bad("umPerPx", "must be positive");
    if (!(spec.sectionPitchUm > 0) || !std::isfinite(spec.sectionPitchUm))
        return bad("sectionPitchUm", "must be positive");
    if (!(spec.sectionWidthUm > 0) || !std::isfinite(spec.sectionWidthUm))
        return bad("sectionWidthUm", "must be positive");
    if (spec.sectionWidthUm > spec.sectionPitchUm)
        return bad("sectionWidthUm", "must not exceed sectionPitchUm");
    if (!(spec.marginUm >= 0) || !std::isfinite(spec.originXUm) || !std::isfinite(spec.originYUm))
        return bad("marginUm", "must be >= 0 (origin finite)");
    const int patchW = static_cast<int>(std::lround(spec.sectionWidthUm / spec.umPerPx));
    const int patchH = static_cast<int>(std::lround(patchW * 0.75));
    // The generator works on 300..10000 px; small patches are generated at 300 and scaled down.
    if (patchW < 16 || patchW > 10'000)
        return bad("sectionWidthUm",
                   "the patch must be 16..10000 px at umPerPx (is " + std::to_string(patchW) + ")");
    for (std::size_t i = 0; i < spec.sections.size(); ++i) {
        const auto& s = spec.sections[i];
        const std::string f = "sections[" + std::to_string(i) + "]";
        if (!(s.apFraction >= 0 && s.apFraction <= 1))
            return bad(f + ".apFraction", "must be in [0, 1]");
        if (s.damage != "" && s.damage != "tear" && s.damage != "missing" && s.damage != "fragment")
            return bad(f + ".damage",
                       "expected \"\", \"tear\", \"missing\" or \"fragment\", got \"" + s.damage +
                           "\"");
    }
    try {
        const int n = static_cast<int>(spec.sections.size());
        const int cols = std::min(spec.columns, n);
        const int rows = (n + spec.columns - 1) / spec.columns;
        const double widthUm = cols * spec.sectionPitchUm + 2 * spec.marginUm;
        const double heightUm = rows * spec.sectionPitchUm + 2 * spec.marginUm;
        VirtualSlide out;
        out.umPerPx = spec.umPerPx;
        out.originXUm = spec.originXUm;
        out.originYUm = spec.originYUm;
        const int type = spec.brightfield ? CV_8UC3 : CV_16UC1;
        out.image =
            cv::Mat(static_cast<int>(std::ceil(heightUm / spec.umPerPx)),
                    static_cast<int>(std::ceil(widthUm / spec.umPerPx)), type, cv::Scalar::all(0));
        cv::Scalar glass = cv::Scalar::all(-1);
        for (int i = 0; i < n; ++i) {
            const auto& s = spec.sections[static_cast<std::size_t>(i)];
            GeneratorOptions o;
            o.seed = s.seed;
            o.imageSize = {std::max(300, patchW), std::max(300, patchH)};
            o.fillFraction = 0.75;
            o.stain = spec.brightfield ? Stain::Brightfield : Stain::Fluorescence;
            o.noise = 0.3; // the camera adds its own noise
            o.landmarkCount = 0;
            o.damage.tear = s.damage == "tear";
            o.damage.missing = s.damage == "missing";
            o.damage.fragment = s.damage == "fragment";
            auto g = generateSection(builtinAtlasPlane(s.apFraction), o);
            if (!g)
                return makeError(g.error().code, "virtual slide: sections[" + std::to_string(i) +
                                                     "]: " + g.error().message);
            cv::Mat patch = g->image;
            if (patch.cols != patchW)
                cv::resize(patch, patch, {patchW, patchH}, 0, 0, cv::INTER_AREA);
            if (glass[0] < 0) {
                glass = borderLevel(patch);
                out.image.setTo(glass);
            }
            const double cxUm = spec.marginUm + (i % spec.columns + 0.5) * spec.sectionPitchUm;
            const double cyUm = spec.marginUm + (i / spec.columns + 0.5) * spec.sectionPitchUm;
            paste(out.image, patch, {cxUm / spec.umPerPx, cyUm / spec.umPerPx}, glass,
                  spec.brightfield);
            out.sections.push_back({i,
                                    {spec.originXUm + cxUm, spec.originYUm + cyUm, 0},
                                    patchW * spec.umPerPx,
                                    patchH * spec.umPerPx,
                                    s.apFraction,
                                    s.damage});
        }
        return out;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("virtual slide: OpenCV: ") + e.what());
    }
}

core::Result<VirtualSlide> loadVirtualSlide(const std::vector<std::filesystem::path>& images,
                                            double umPerPx, int columns, double pitchUm) {
    if (images.empty())
        return bad("images", "no images");
    if (columns < 1)
        return bad("columns", "must be >= 1");
    if (!(umPerPx > 0) || !std::isfinite(umPerPx))
        return bad("umPerPx", "must be positive");
    if (!(pitchUm > 0) || !std::isfinite(pitchUm))
        return bad("pitchUm", "must be positive");
    std::vector<cv::Mat> mats;
    bool colour = false;
    for (const auto& p : images) {
        auto m = core::readImage(p);
        if (!m)
            return makeError(m.error().code, "virtual slide: " + m.error().message,
                             m.error().sysErrno);
        cv::Mat img = *m;
        if (img.channels() == 2 ||
            (img.channels() > 4)) { // fluorescence channels: the first shows tissue
            cv::extractChannel(img, img, 0);
        } else if (img.channels() == 4) {
            cv::cvtColor(img, img, cv::COLOR_BGRA2BGR);
        }
        if (img.depth() != CV_8U && img.depth() != CV_16U) {
            double mn = 0, mx = 0;
            cv::minMaxLoc(img.reshape(1), &mn, &mx);
            img.convertTo(img, CV_16U, mx > mn ? 65535.0 / (mx - mn) : 1.0,
                          mx > mn ? -mn * 65535.0 / (mx - mn) : 0);
        }
        colour = colour || img.channels() == 3;
        if (img.cols * umPerPx > pitchUm || img.rows * umPerPx > pitchUm)
            return bad("images", p.string() + " (" + std::to_string(img.cols) + "x" +
                                     std::to_string(img.rows) + " px) is larger than its " +
                                     std::to_string(pitchUm) + " um cell");
        mats.push_back(img);
    }
    try {
        for (auto& m : mats) {
            if (colour) {
                if (m.depth() == CV_16U)
                    m.convertTo(m, CV_8U, 1.0 / 257);
                if (m.channels() == 1)
                    cv::cvtColor(m, m, cv::COLOR_GRAY2BGR);
            } else if (m.depth() == CV_8U) {
                m.convertTo(m, CV_16U, 257);
            }
        }
        // Glass: the median of every image's border level.
        std::vector<cv::Scalar> levels;
        for (const auto& m : mats)
            levels.push_back(borderLevel(m));
        cv::Scalar glass;
        for (int c = 0; c < 3; ++c) {
            std::vector<double> v;
            for (const auto& l : levels)
                v.push_back(l[c]);
            std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2),
                             v.end());
            glass[c] = v[v.size() / 2];
        }
        const int n = static_cast<int>(mats.size());
        const int cols = std::min(columns, n), rows = (n + columns - 1) / columns;
        VirtualSlide out;
        out.umPerPx = umPerPx;
        out.originXUm = out.originYUm = 0;
        out.image = cv::Mat(static_cast<int>(std::ceil(rows * pitchUm / umPerPx)),
                            static_cast<int>(std::ceil(cols * pitchUm / umPerPx)),
                            colour ? CV_8UC3 : CV_16UC1, glass);
        for (int i = 0; i < n; ++i) {
            const double cxUm = (i % columns + 0.5) * pitchUm, cyUm = (i / columns + 0.5) * pitchUm;
            const cv::Mat& m = mats[static_cast<std::size_t>(i)];
            // Real images keep their own glass: copied as they are, not re-levelled.
            const cv::Rect r(static_cast<int>(std::lround(cxUm / umPerPx - m.cols / 2.0)),
                             static_cast<int>(std::lround(cyUm / umPerPx - m.rows / 2.0)), m.cols,
                             m.rows);
            const cv::Rect clipped = r & cv::Rect(0, 0, out.image.cols, out.image.rows);
            m(cv::Rect(clipped.x - r.x, clipped.y - r.y, clipped.width, clipped.height))
                .copyTo(out.image(clipped));
            out.sections.push_back(
                {i, {cxUm, cyUm, 0}, m.cols * umPerPx, m.rows * umPerPx, -1.0, ""});
        }
        return out;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("virtual slide: OpenCV: ") + e.what());
    }
}

} // namespace slicestation::sim
