#include "slicestation/pipeline/cells.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <map>
#include <string>
#include <unordered_map>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

/// One plane of `image` as CV_32F, channel in file order (RGB), -1 = grey.
core::Result<cv::Mat> planeOf(const cv::Mat& image, int channel) {
    const int n = image.channels();
    const int depth = image.depth();
    if (depth != CV_8U && depth != CV_16U && depth != CV_32F)
        return makeError(ErrorCode::InvalidArgument,
                         "cell detection needs an 8-bit, 16-bit or float image");
    if (n != 1 && n != 3 && n != 4)
        return makeError(ErrorCode::InvalidArgument,
                         "cell detection needs 1, 3 or 4 channels, not " + std::to_string(n));
    if (channel < -1 || channel >= n)
        return makeError(ErrorCode::InvalidArgument,
                         "channel " + std::to_string(channel) + " is not in an image of " +
                             std::to_string(n) + " channel" + (n == 1 ? "" : "s") + " (0.." +
                             std::to_string(n - 1) + ")");
    cv::Mat plane;
    if (n == 1) {
        plane = image;
    } else if (channel < 0) {
        cv::cvtColor(image, plane, n == 3 ? cv::COLOR_BGR2GRAY : cv::COLOR_BGRA2GRAY);
    } else {
        // OpenCV keeps colour as BGR(A); the user counts channels as the file does (RGB(A)).
        const int bgr = channel < 3 ? 2 - channel : channel;
        cv::extractChannel(image, plane, bgr);
    }
    cv::Mat f;
    plane.convertTo(f, CV_32F);
    return f;
}

double median(std::vector<float>& v) {
    if (v.empty())
        return 0;
    const auto mid = v.begin() + std::ptrdiff_t(v.size() / 2);
    std::nth_element(v.begin(), mid, v.end());
    return *mid;
}

std::vector<float> valuesIn(const cv::Mat& f, const cv::Mat& mask, int stride = 1) {
    std::vector<float> v;
    v.reserve(size_t(f.total() / size_t(stride * stride)) + 1);
    for (int y = 0; y < f.rows; y += stride) {
        const float* p = f.ptr<float>(y);
        const std::uint8_t* m = mask.empty() ? nullptr : mask.ptr<std::uint8_t>(y);
        for (int x = 0; x < f.cols; x += stride)
            if (!m || m[x])
                v.push_back(p[x]);
    }
    return v;
}

/// 1.4826 x median absolute deviation: the standard deviation of Gaussian noise, unmoved by a
/// few bright cells.
double robustSigma(const cv::Mat& f, const cv::Mat& mask) {
    const int stride = f.total() > 4'000'000 ? 2 : 1;
    std::vector<float> v = valuesIn(f, mask, stride);
    const double med = median(v);
    for (float& x : v)
        x = std::abs(x - float(med));
    return 1.4826 * median(v);
}

/// Glass brighter than tissue: brightfield, cells absorb.
bool cellsDark(const cv::Mat& f, const cv::Mat& mask) {
    if (!mask.empty() && cv::countNonZero(mask) > 0 && cv::countNonZero(mask == 0) > 0) {
        std::vector<float> in = valuesIn(f, mask, 2), out = valuesIn(f, mask == 0, 2);
        return median(out) > median(in);
    }
    // No mask: the image's border is mostly glass.
    const int b = std::max(2, std::min(f.rows, f.cols) / 30);
    cv::Mat border = cv::Mat::zeros(f.size(), CV_8U);
    border.setTo(255);
    border(cv::Rect(b, b, f.cols - 2 * b, f.rows - 2 * b)).setTo(0);
    std::vector<float> edge = valuesIn(f, border, 2), all = valuesIn(f, cv::Mat(), 2);
    return median(edge) > median(all);
}

int oddAtLeast3(double v) {
    int k = std::max(3, int(std::lround(v)));
    return k % 2 ? k : k + 1;
}

/// Local background removed: white top-hat with a disc wider than a cell, so cells stay and
/// slow stain variations (regions, illumination) go.
cv::Mat backgroundSubtracted(const cv::Mat& f, double diameterPx) {
    const int k = oddAtLeast3(2.5 * diameterPx);
    cv::Mat out;
    cv::morphologyEx(f, out, cv::MORPH_TOPHAT,
                     cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(k, k)));
    return out;
}

/// k-means (Lloyd) of `pixels` (weights `w`) into centres seeded with `centres` and, for the
/// missing ones, the pixel farthest from every centre so far.
std::vector<cv::Point2d> kMeans(const std::vector<cv::Point2d>& pixels, const std::vector<float>& w,
                                std::vector<cv::Point2d> centres, size_t count) {
    auto nearest = [&centres](const cv::Point2d& p) {
        size_t best = 0;
        for (size_t c = 1; c < centres.size(); ++c)
            if (cv::norm(p - centres[c]) < cv::norm(p - centres[best]))
                best = c;
        return best;
    };
    while (centres.size() < count) {
        size_t far = 0;
        double farD = -1;
        for (size_t i = 0; i < pixels.size(); ++i) {
            const double d = cv::norm(pixels[i] - centres[nearest(pixels[i])]);
            if (d > farD) {
                farD = d;
                far = i;
            }
        }
        centres.push_back(pixels[far]);
    }
    for (int it = 0; it < 10; ++it) {
        std::vector<cv::Point2d> sum(centres.size(), {0, 0});
        std::vector<double> weight(centres.size(), 0);
        for (size_t i = 0; i < pixels.size(); ++i) {
            const size_t c = nearest(pixels[i]);
            sum[c] += pixels[i] * double(w[i]);
            weight[c] += w[i];
        }
        for (size_t c = 0; c < centres.size(); ++c)
            if (weight[c] > 0)
                centres[c] = sum[c] / weight[c];
    }
    return centres;
}

/// Touching cells closer than about 1.1 diameters give one LoG maximum (their sum has one peak,
/// and the stain saturates between them): the area tells them apart. Each detection's blob is
/// the connected set of pixels above half the brightest pixel within 0.75 diameters (the
/// half-maximum outline of the cell it belongs to). A blob of k detections and n >= k + 1 times
/// the median area of one-detection blobs holds n cells, placed by k-means over its pixels
/// (weighted by brightness, seeded with the detections). Blobs of more than kMaxBlobCells cells
/// are stain, not cells, and are left as found.
std::vector<DetectedCell> splitTouching(std::vector<DetectedCell> cells, const cv::Mat& top,
                                        const cv::Mat& mask, const CellDetectorOptions& o) {
    constexpr double kMaxBlobCells = 6;
    if (!(o.splitAt > 0) || cells.size() < 20)
        return cells;
    const int r = std::max(1, int(std::lround(0.75 * o.diameterPx)));
    cv::Mat peak;
    cv::dilate(top, peak,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1)));
    cv::Mat half = (top >= peak * 0.5) & (top > 0);
    if (!mask.empty())
        half &= mask != 0;
    cv::Mat labels, stats, centroids;
    const int n = cv::connectedComponentsWithStats(half, labels, stats, centroids, 8, CV_32S);
    std::vector<std::vector<size_t>> members(static_cast<size_t>(n));
    for (size_t i = 0; i < cells.size(); ++i) {
        const int x = int(std::lround(cells[i].imagePx.x)),
                  y = int(std::lround(cells[i].imagePx.y));
        if (x >= 0 && y >= 0 && x < labels.cols && y < labels.rows && labels.at<int>(y, x) > 0)
            members[size_t(labels.at<int>(y, x))].push_back(i);
    }
    std::vector<float> singles;
    for (int l = 1; l < n; ++l)
        if (members[size_t(l)].size() == 1)
            singles.push_back(float(stats.at<int>(l, cv::CC_STAT_AREA)));
    if (singles.size() < 10)
        return cells;
    const double cellArea = std::max(1.0, median(singles));
    std::vector<DetectedCell> out;
    std::vector<char> replaced(cells.size(), 0);
    for (int l = 1; l < n; ++l) {
        const auto& m = members[size_t(l)];
        const double ratio = stats.at<int>(l, cv::CC_STAT_AREA) / cellArea;
        const auto want = size_t(std::floor(ratio + 2 - o.splitAt));
        if (m.empty() || want <= m.size() || ratio > kMaxBlobCells)
            continue;
        const cv::Rect box(stats.at<int>(l, cv::CC_STAT_LEFT), stats.at<int>(l, cv::CC_STAT_TOP),
                           stats.at<int>(l, cv::CC_STAT_WIDTH),
                           stats.at<int>(l, cv::CC_STAT_HEIGHT));
        std::vector<cv::Point2d> pixels;
        std::vector<float> weights;
        for (int y = box.y; y < box.y + box.height; ++y)
            for (int x = box.x; x < box.x + box.width; ++x)
                if (labels.at<int>(y, x) == l) {
                    pixels.emplace_back(x, y);
                    weights.push_back(top.at<float>(y, x));
                }
        std::vector<cv::Point2d> seeds;
        double response = 0;
        for (size_t i : m) {
            seeds.push_back(cells[i].imagePx);
            response = std::max(response, cells[i].response);
            replaced[i] = 1;
        }
        for (const cv::Point2d& c : kMeans(pixels, weights, seeds, want))
            out.push_back({c, response, 1});
    }
    for (size_t i = 0; i < cells.size(); ++i)
        if (!replaced[i])
            out.push_back(cells[i]);
    return out;
}

/// The pixels at an integer format's ceiling, and what judging them needs.
struct Clipping {
    cv::Mat mask;       ///< CV_8U, non-zero = clipped; empty for float images (no known ceiling)
    cv::Mat plane;      ///< the detector's plane (inverted for dark cells), CV_32F
    double ceiling = 0; ///< the plane's value at a clipped pixel
};

/// Detections for clipped cell cores that no detection holds yet. A pixel at the sensor's
/// ceiling says only "at least this bright": a labelled cell clipped on a bright, textured
/// background (a Nissl stain: every cell body stained, dense, touching) answers the LoG with the
/// clipped height alone, which the texture matches, so its signal-to-noise ratio falls under the
/// threshold. What tells a clipped cell from clipped stain is the cell body's own profile, a
/// Gaussian of FWHM d (s = d / 2.3548):
/// - its core: a cell clips over a disc, so its clipped piece holds pixels at least d/3 from any
///   unclipped pixel (every pixel within d/3 of them is clipped); stain grains and noise clip
///   in specks and threads. Each connected set of such core pixels is one cell (touching
///   clipped cells keep one core each where their neck is thinner than 2 d/3);
/// - its shoulder: clipped out to d/3, the cell is at least (ceiling - background) / g(d/3)
///   tall, g(r) = exp(-r^2 / 2 s^2), g(d/3) = 0.735; so at its half-maximum radius d/2 it
///   still stands 0.5 / 0.735 = 0.68 of the headroom above the local background (the top-hat's
///   opening). The median of 16 samples on that circle must reach it: a clump of stain grains
///   falls off sooner. Where the background itself is at the ceiling, clipping tells nothing.
/// A core that holds no detection and has none within the separation of its centre becomes a
/// cell there. Run after the area split.
std::vector<DetectedCell> addClippedCells(std::vector<DetectedCell> cells, const Clipping& clip,
                                          const cv::Mat& top, const cv::Mat& mask,
                                          const CellDetectorOptions& o, double response) {
    // The core radius, x diameter: where a Gaussian cell body is at 0.735 of its peak. Of 1/3,
    // 0.37 and 0.42 (the discrete distances of a 6 px cell: 2, 2.24, 2.5 px) 1/3 was best on
    // the Nissl sections of generated family 2's cases 0-23 (docs/cells.md).
    constexpr double kCoreRadius = 1.0 / 3;
    if (clip.mask.empty())
        return cells;
    const double s = 1.0 / 2.3548; // the profile's sigma, x diameter
    const double shoulder = 0.5 / std::exp(-kCoreRadius * kCoreRadius / (2 * s * s));
    cv::Mat pieces = clip.mask.clone();
    if (!mask.empty())
        pieces &= mask != 0;
    cv::Mat distance;
    cv::distanceTransform(pieces, distance, cv::DIST_L2, cv::DIST_MASK_PRECISE);
    const cv::Mat cores = distance >= kCoreRadius * o.diameterPx;
    cv::Mat labels, stats, centroids;
    const int n = cv::connectedComponentsWithStats(cores, labels, stats, centroids, 8, CV_32S);
    std::vector<char> held(static_cast<size_t>(n), 0);
    for (const DetectedCell& c : cells) {
        const int x = int(std::lround(c.imagePx.x)), y = int(std::lround(c.imagePx.y));
        if (x >= 0 && y >= 0 && x < labels.cols && y < labels.rows)
            held[size_t(labels.at<int>(y, x))] = 1;
    }
    const double sep = o.minSeparation * o.diameterPx;
    const size_t found = cells.size();
    for (int l = 1; l < n; ++l) {
        if (held[size_t(l)])
            continue;
        const cv::Point2d centre(centroids.at<double>(l, 0), centroids.at<double>(l, 1));
        bool near = false;
        for (size_t i = 0; i < found && !near; ++i)
            near = cv::norm(cells[i].imagePx - centre) < sep;
        if (near)
            continue;
        const cv::Point c(int(std::lround(centre.x)), int(std::lround(centre.y)));
        const double background = clip.plane.at<float>(c) - top.at<float>(c);
        const double headroom = clip.ceiling - background;
        if (!(headroom > 0))
            continue;
        std::vector<float> ring;
        for (int a = 0; a < 16; ++a) {
            const double t = a * CV_PI / 8;
            const cv::Point2f q(float(centre.x + 0.5 * o.diameterPx * std::cos(t)),
                                float(centre.y + 0.5 * o.diameterPx * std::sin(t)));
            cv::Mat px;
            cv::getRectSubPix(clip.plane, {1, 1}, q, px);
            ring.push_back(px.at<float>(0, 0));
        }
        if ((median(ring) - background) / headroom >= shoulder)
            cells.push_back({centre, response, 1});
    }
    return cells;
}

std::vector<DetectedCell> detectLoG(const cv::Mat& top, const cv::Mat& mask, const Clipping& clip,
                                    const CellDetectorOptions& o) {
    // A disc of radius r answers most strongly at sigma = r / sqrt(2) (Lindeberg's scale
    // selection); the response is scale-normalised (sigma^2).
    const double sigma = o.diameterPx / (2.0 * std::sqrt(2.0));
    auto logAt = [&top](double s) {
        cv::Mat blurred, lap;
        cv::GaussianBlur(top, blurred, cv::Size(), s);
        cv::Laplacian(blurred, lap, CV_32F, 3);
        return cv::Mat(lap * -(s * s));
    };
    cv::Mat response = logAt(sigma);
    // Scale selection: a cell answers at its own scale clearly more than at half of it; stain
    // texture (nuclei of the counterstain, speckle) is smaller and answers more at the finer
    // scale.
    const cv::Mat finer = logAt(0.5 * sigma);
    // A blob of the cell's size (FWHM = diameter) answers about 1.9 times more at sigma than at
    // sigma / 2, a nucleus of a third of it about half as much: 1.7 keeps cells with a margin
    // (chosen on generated family 1: precision 0.886 -> 0.970 at the same recall, 1.9 lost
    // recall; slst_bench_cells).
    constexpr double kScaleRatio = 1.7;
    const cv::Mat cellSized = response >= finer * kScaleRatio;
    // The response in units of its local spread: the robust spread (1.4826 x MAD) in tiles of
    // ~10 cell diameters over the searched pixels, interpolated between tile centres. Stain
    // texture differs between regions, so one global noise figure either misses cells in quiet
    // regions or takes texture for cells in busy ones; a median keeps the cells themselves
    // (a few percent of the pixels) mostly out of it. Tiles
    // with little tissue take the global figure.
    const double globalNoise = std::max(1e-12, robustSigma(response, mask));
    const int tile = std::max(16, int(std::lround(10 * o.diameterPx)));
    const int tilesX = (response.cols + tile - 1) / tile,
              tilesY = (response.rows + tile - 1) / tile;
    cv::Mat tileNoise(tilesY, tilesX, CV_32F);
    for (int ty = 0; ty < tilesY; ++ty)
        for (int tx = 0; tx < tilesX; ++tx) {
            const cv::Rect r = cv::Rect(tx * tile, ty * tile, tile, tile) &
                               cv::Rect(0, 0, response.cols, response.rows);
            std::vector<float> v = valuesIn(response(r), mask.empty() ? cv::Mat() : mask(r));
            double n = globalNoise;
            if (v.size() * 4 >= size_t(r.area())) {
                const double med = median(v);
                // Symmetric: the lower half alone (cells are outliers above only) gained 3 points
                // of median error on family 1 but took texture for cells on the built-in atlas
                // (+27% instead of +17% in test_slicectl_count).
                for (float& x : v)
                    x = std::abs(x - float(med));
                n = std::max(0.5 * globalNoise, 1.4826 * median(v));
            }
            tileNoise.at<float>(ty, tx) = float(n);
        }
    cv::Mat localNoise;
    cv::resize(tileNoise, localNoise, response.size(), 0, 0, cv::INTER_LINEAR);
    cv::Mat snr = response / localNoise;
    const double noise = 1.0, threshold = o.minSnr;
    response = snr;

    // Non-maximum suppression: a maximum over the disc of radius minSeparation x diameter.
    const int radius = std::max(1, int(std::lround(o.minSeparation * o.diameterPx)));
    cv::Mat dilated;
    cv::dilate(
        response, dilated,
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1)));
    std::vector<DetectedCell> found;
    for (int y = 1; y + 1 < response.rows; ++y) {
        const float* r = response.ptr<float>(y);
        const float* d = dilated.ptr<float>(y);
        const std::uint8_t* m = mask.empty() ? nullptr : mask.ptr<std::uint8_t>(y);
        for (int x = 1; x + 1 < response.cols; ++x) {
            if (r[x] < threshold || r[x] < d[x] || (m && !m[x]) ||
                !cellSized.at<std::uint8_t>(y, x))
                continue;
            // Sub-pixel: the vertex of a parabola through the maximum and its neighbours.
            const float* up = response.ptr<float>(y - 1);
            const float* dn = response.ptr<float>(y + 1);
            auto offset = [](double a, double b, double c) {
                const double den = a - 2 * b + c;
                return den < 0 ? std::clamp(0.5 * (a - c) / den, -0.5, 0.5) : 0.0;
            };
            DetectedCell cell;
            cell.imagePx = {x + offset(r[x - 1], r[x], r[x + 1]), y + offset(up[x], r[x], dn[x])};
            cell.response = r[x] / noise;
            found.push_back(cell);
        }
    }
    // Plateaus (a saturated cell) give several equal maxima: keep the strongest of any group
    // closer than the separation.
    std::sort(found.begin(), found.end(),
              [](const DetectedCell& a, const DetectedCell& b) { return a.response > b.response; });
    const double sep = o.minSeparation * o.diameterPx;
    const double cellSize = std::max(1.0, sep);
    std::unordered_map<std::int64_t, std::vector<cv::Point2d>> grid;
    auto key = [](std::int64_t gx, std::int64_t gy) { return gx * 1'000'003 + gy; };
    std::vector<DetectedCell> kept;
    for (const DetectedCell& c : found) {
        const auto gx = std::int64_t(std::floor(c.imagePx.x / cellSize));
        const auto gy = std::int64_t(std::floor(c.imagePx.y / cellSize));
        bool close = false;
        for (std::int64_t i = -1; i <= 1 && !close; ++i)
            for (std::int64_t j = -1; j <= 1 && !close; ++j) {
                auto it = grid.find(key(gx + i, gy + j));
                if (it == grid.end())
                    continue;
                for (const cv::Point2d& p : it->second)
                    if (cv::norm(p - c.imagePx) < sep) {
                        close = true;
                        break;
                    }
            }
        if (close)
            continue;
        grid[key(gx, gy)].push_back(c.imagePx);
        kept.push_back(c);
    }
    kept = splitTouching(std::move(kept), top, mask, o);
    kept = addClippedCells(std::move(kept), clip, top, mask, o, threshold);
    std::sort(kept.begin(), kept.end(), [](const DetectedCell& a, const DetectedCell& b) {
        return a.imagePx.y != b.imagePx.y ? a.imagePx.y < b.imagePx.y : a.imagePx.x < b.imagePx.x;
    });
    return kept;
}

std::vector<DetectedCell> detectThreshold(const cv::Mat& top, const cv::Mat& mask,
                                          const CellDetectorOptions& o) {
    // The top-hat of noise alone is not centred on 0: measure from its median.
    std::vector<float> values = valuesIn(top, mask, top.total() > 4'000'000 ? 2 : 1);
    const double level = median(values);
    const double noise = std::max(1e-12, robustSigma(top, mask));
    cv::Mat binary = top > level + o.minSnr * noise;
    if (!mask.empty())
        binary.setTo(0, mask == 0);
    cv::Mat labels, stats, centroids;
    const int n = cv::connectedComponentsWithStats(binary, labels, stats, centroids, 8, CV_32S);
    std::vector<float> areas;
    for (int i = 1; i < n; ++i)
        if (stats.at<int>(i, cv::CC_STAT_AREA) >= o.minClusterPx)
            areas.push_back(float(stats.at<int>(i, cv::CC_STAT_AREA)));
    if (areas.empty())
        return {};
    std::vector<float> sorted = areas;
    const double cellArea = std::max(1.0, median(sorted));
    std::vector<float> peaks(size_t(n), 0.f);
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        const float* t = top.ptr<float>(y);
        for (int x = 0; x < labels.cols; ++x)
            if (l[x] > 0)
                peaks[size_t(l[x])] = std::max(peaks[size_t(l[x])], t[x]);
    }
    std::vector<DetectedCell> out;
    for (int i = 1; i < n; ++i) {
        const int area = stats.at<int>(i, cv::CC_STAT_AREA);
        if (area < o.minClusterPx)
            continue;
        DetectedCell c;
        c.imagePx = {centroids.at<double>(i, 0), centroids.at<double>(i, 1)};
        c.clusterCells = std::max(1, int(std::lround(area / cellArea)));
        c.response = (peaks[size_t(i)] - level) / noise;
        out.push_back(c);
    }
    return out;
}

} // namespace

std::string_view toString(CellPolarity p) noexcept {
    switch (p) {
    case CellPolarity::Bright:
        return "bright";
    case CellPolarity::Dark:
        return "dark";
    case CellPolarity::Auto:
        break;
    }
    return "auto";
}

std::string_view toString(CellMethod m) noexcept {
    return m == CellMethod::Threshold ? "threshold" : "log";
}

core::Result<std::vector<DetectedCell>> detectCells(const cv::Mat& image,
                                                    const CellDetectorOptions& o) {
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, "cell detection: the image is empty");
    if (!(o.diameterPx >= 2 && o.diameterPx <= 200))
        return makeError(ErrorCode::InvalidArgument, "cell diameter must be in [2, 200] px, not " +
                                                         std::to_string(o.diameterPx));
    if (!(o.minSnr > 0 && o.minSnr <= 1000))
        return makeError(ErrorCode::InvalidArgument, "cell minSnr must be in (0, 1000]");
    if (!(o.minSeparation > 0 && o.minSeparation <= 5))
        return makeError(ErrorCode::InvalidArgument, "cell minSeparation must be in (0, 5]");
    if (!(o.splitAt == 0 || (o.splitAt >= 1 && o.splitAt <= 2)))
        return makeError(ErrorCode::InvalidArgument, "cell splitAt must be 0 or in [1, 2]");
    if (o.minClusterPx < 1 || o.minClusterPx > 100000)
        return makeError(ErrorCode::InvalidArgument, "cell minClusterPx must be in [1, 100000]");
    if (!o.mask.empty() && (o.mask.size() != image.size() || o.mask.type() != CV_8U))
        return makeError(ErrorCode::InvalidArgument,
                         "cell detection mask must be CV_8U of the image's size");
    try {
        auto plane = planeOf(image, o.channel);
        if (!plane)
            return plane.error();
        cv::Mat f = *plane;
        const bool dark = o.polarity == CellPolarity::Dark ||
                          (o.polarity == CellPolarity::Auto && cellsDark(f, o.mask));
        // Pixels at the integer format's ceiling (bright cells) or floor (dark cells that let
        // no light through) are clipped: their true value lies beyond the bound.
        Clipping clip;
        clip.ceiling = image.depth() == CV_8U ? 255 : 65535;
        if (image.depth() != CV_32F)
            clip.mask = dark ? f <= 0 : f >= clip.ceiling;
        if (dark) {
            double hi = 0;
            cv::minMaxLoc(f, nullptr, &hi);
            f = hi - f;
            clip.ceiling = hi; // a pixel at 0 (no light through) is at hi once inverted
        }
        clip.plane = f;
        const cv::Mat top = backgroundSubtracted(f, o.diameterPx);
        return o.method == CellMethod::LoG ? detectLoG(top, o.mask, clip, o)
                                           : detectThreshold(top, o.mask, o);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("cell detection: OpenCV: ") + e.what());
    }
}

std::vector<RegionCount> rollUp(const std::vector<RegionCount>& leaves,
                                const core::Ontology& ontology) {
    std::map<std::uint32_t, RegionCount> totals;
    for (const RegionCount& leaf : leaves) {
        const core::Structure* s = ontology.find(leaf.id);
        if (!s) {
            RegionCount& t = totals[leaf.id];
            t.id = leaf.id;
            t.cells += leaf.cells;
            t.areaPx += leaf.areaPx;
            continue;
        }
        for (std::uint32_t a : s->path) {
            RegionCount& t = totals[a];
            t.id = a;
            t.cells += leaf.cells;
            t.areaPx += leaf.areaPx;
        }
    }
    std::vector<RegionCount> out;
    out.reserve(totals.size());
    for (const core::Structure& s : ontology.structures()) {
        auto it = totals.find(s.id);
        if (it == totals.end())
            continue;
        it->second.parentId = s.parentId;
        it->second.depth = int(s.path.size()) - 1;
        out.push_back(it->second);
        totals.erase(it);
    }
    for (const auto& [id, t] : totals) // ids the ontology lacks, increasing
        out.push_back(t);
    return out;
}

core::Result<CellTable> countCells(const Registration& reg, const cv::Mat& atlasLabels,
                                   const std::vector<DetectedCell>& cells,
                                   const core::Ontology& ontology) {
    if (atlasLabels.empty() || atlasLabels.type() != CV_32S)
        return makeError(ErrorCode::InvalidArgument,
                         "cell counting: atlas labels must be a non-empty CV_32S image");
    if (reg.workingTissueMask.empty() || reg.workingTissueMask.type() != CV_8U ||
        !(reg.workingScale > 0) || reg.imageSize.empty())
        return makeError(ErrorCode::InvalidArgument,
                         "cell counting: the registration holds no working tissue mask");
    try {
        const cv::Size ws = reg.workingTissueMask.size();
        const cv::Mat labels = reg.warpedLabels(atlasLabels, ws);
        // Damage polygons are in section px; draw them on the working grid.
        cv::Mat damaged = cv::Mat::zeros(ws, CV_8U);
        for (const DamageRegion& d : reg.damage) {
            std::vector<cv::Point> poly;
            for (const cv::Point2f& p : d.polygon) {
                const cv::Point2d w = reg.workingFromImage(p);
                poly.emplace_back(int(std::lround(w.x)), int(std::lround(w.y)));
            }
            if (poly.size() >= 3)
                cv::fillPoly(damaged, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
        }
        CellTable table;
        std::map<std::uint32_t, RegionCount> leaves;
        const double pxArea = 1.0 / (reg.workingScale * reg.workingScale);
        for (int y = 0; y < ws.height; ++y) {
            const std::uint8_t* t = reg.workingTissueMask.ptr<std::uint8_t>(y);
            const std::uint8_t* dm = damaged.ptr<std::uint8_t>(y);
            const std::int32_t* l = labels.ptr<std::int32_t>(y);
            for (int x = 0; x < ws.width; ++x) {
                if (!t[x] || l[x] <= 0)
                    continue;
                if (dm[x]) {
                    table.excludedAreaPx += pxArea;
                    continue;
                }
                RegionCount& r = leaves[std::uint32_t(l[x])];
                r.id = std::uint32_t(l[x]);
                r.areaPx += pxArea;
                table.tissueAreaPx += pxArea;
            }
        }
        for (const DetectedCell& c : cells) {
            MappedCell m;
            m.imagePx = c.imagePx;
            m.cells = c.clusterCells;
            m.atlasPx = reg.atlasFromImage(c.imagePx);
            const int ax = int(std::lround(m.atlasPx.x)), ay = int(std::lround(m.atlasPx.y));
            if (ax >= 0 && ay >= 0 && ax < atlasLabels.cols && ay < atlasLabels.rows)
                m.atlasId = std::max(0, atlasLabels.at<std::int32_t>(ay, ax));
            for (const DamageRegion& d : reg.damage)
                if (d.polygon.size() >= 3 &&
                    cv::pointPolygonTest(d.polygon, cv::Point2f(c.imagePx), false) >= 0) {
                    m.excluded = true;
                    break;
                }
            if (m.excluded) {
                table.excludedCells += m.cells;
            } else if (m.atlasId > 0) {
                RegionCount& r = leaves[std::uint32_t(m.atlasId)];
                r.id = std::uint32_t(m.atlasId);
                r.cells += m.cells;
            }
            table.cells.push_back(m);
        }
        std::vector<RegionCount> leafRows;
        for (const auto& [id, r] : leaves)
            leafRows.push_back(r);
        table.regions = rollUp(leafRows, ontology);
        return table;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("cell counting: OpenCV: ") + e.what());
    }
}

} // namespace slicestation::pipeline
