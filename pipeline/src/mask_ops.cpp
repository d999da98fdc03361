#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace slicestation::pipeline {

cv::Mat weightedLocalMean(const cv::Mat& values, const cv::Mat& weight, double sigma, int factor) {
    CV_Assert(values.type() == CV_32F && weight.type() == CV_32F &&
              values.size() == weight.size() && sigma > 0 && factor >= 1);
    const cv::Size small((values.cols + factor - 1) / factor, (values.rows + factor - 1) / factor);
    cv::Mat num, den;
    cv::resize(values.mul(weight), num, small, 0, 0, cv::INTER_AREA);
    cv::resize(weight, den, small, 0, 0, cv::INTER_AREA);
    const double s = sigma / factor;
    cv::GaussianBlur(num, num, cv::Size(), s, s, cv::BORDER_REPLICATE);
    cv::GaussianBlur(den, den, cv::Size(), s, s, cv::BORDER_REPLICATE);
    cv::Mat mean;
    cv::divide(num, den + 1e-6, mean);
    cv::resize(mean, mean, values.size(), 0, 0, cv::INTER_LINEAR);
    return mean;
}

cv::Mat fillHoles(const cv::Mat& mask) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(mask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    cv::Mat filled = cv::Mat::zeros(mask.size(), CV_8U);
    cv::drawContours(filled, contours, -1, cv::Scalar(255), cv::FILLED);
    return filled;
}

std::vector<cv::Point2f> outerContourPoints(const cv::Mat& mask) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(mask.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    std::vector<cv::Point2f> out;
    for (const auto& c : contours)
        for (const auto& p : c)
            out.emplace_back(float(p.x), float(p.y));
    return out;
}

float kthSmallest(std::vector<float>& values, size_t k) {
    CV_Assert(k < values.size());
    if (values.size() < 8192) {
        std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k),
                         values.end());
        return values[k];
    }
    // The float's bits made an unsigned key that sorts as the float does: its top 16 bits
    // pick the bucket holding the k-th value, and only that bucket is selected in.
    const auto key = [](float f) {
        std::uint32_t u;
        std::memcpy(&u, &f, sizeof u);
        return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    };
    std::vector<std::uint32_t> count(65536, 0);
    for (const float f : values)
        ++count[key(f) >> 16];
    size_t below = 0;
    std::uint32_t bucket = 0;
    while (below + count[bucket] <= k)
        below += count[bucket++];
    std::vector<float> inBucket;
    inBucket.reserve(count[bucket]);
    for (const float f : values)
        if ((key(f) >> 16) == bucket)
            inBucket.push_back(f);
    const size_t j = k - below;
    std::nth_element(inBucket.begin(), inBucket.begin() + static_cast<std::ptrdiff_t>(j),
                     inBucket.end());
    return inBucket[j];
}

float percentile(const cv::Mat& f32, double q, const cv::Mat& valid) {
    std::vector<float> v;
    v.reserve(f32.total());
    // A strided sample is plenty for a percentile and keeps this cheap on large images.
    const int step = std::max(1, static_cast<int>(std::sqrt(f32.total() / 250000.0)));
    for (int y = 0; y < f32.rows; y += step) {
        const float* row = f32.ptr<float>(y);
        const uchar* ok = valid.ptr<uchar>(y);
        for (int x = 0; x < f32.cols; x += step)
            if (ok[x])
                v.push_back(row[x]);
    }
    if (v.empty())
        return 0.0f;
    auto k = static_cast<size_t>(std::clamp(q, 0.0, 1.0) * static_cast<double>(v.size() - 1));
    return kthSmallest(v, k);
}

namespace {

/// A horizontal run of set pixels: row y, columns [x0, x1).
struct Run {
    int y, x0, x1;
};

/// The runs of set pixels of one row, appended to `runs`. Zero bytes are skipped eight at a
/// time: the masks labelled here are mostly empty.
void appendRuns(const std::uint8_t* row, int cols, int y, std::vector<Run>& runs) {
    int x = 0;
    while (x < cols) {
        while (x + 8 <= cols) {
            std::uint64_t word;
            std::memcpy(&word, row + x, sizeof word);
            if (word != 0)
                break;
            x += 8;
        }
        while (x < cols && !row[x])
            ++x;
        if (x >= cols)
            break;
        const int x0 = x;
        while (x < cols && row[x])
            ++x;
        runs.push_back({y, x0, x});
    }
}

int findRoot(std::vector<int>& parent, int i) {
    while (parent[static_cast<std::size_t>(i)] != i) {
        int& p = parent[static_cast<std::size_t>(i)];
        p = parent[static_cast<std::size_t>(p)]; // path halving
        i = p;
    }
    return i;
}

} // namespace

int labelComponents(const cv::Mat& mask, cv::Mat& labels, cv::Mat& stats) {
    CV_Assert(mask.type() == CV_8U);
    // The runs of each row, and the runs 8-connected across consecutive rows joined (union-find
    // over run indices, the smaller index the root).
    std::vector<Run> runs;
    std::vector<int> parent;
    std::size_t prevBegin = 0, prevEnd = 0;
    for (int y = 0; y < mask.rows; ++y) {
        const std::size_t begin = runs.size();
        appendRuns(mask.ptr<std::uint8_t>(y), mask.cols, y, runs);
        const std::size_t end = runs.size();
        for (std::size_t i = begin; i < end; ++i)
            parent.push_back(static_cast<int>(i));
        // Two runs of consecutive rows touch (8-connected) when each starts at most one pixel
        // past the other's end.
        std::size_t q = prevBegin;
        for (std::size_t r = begin; r < end && q < prevEnd;) {
            if (runs[q].x1 < runs[r].x0) {
                ++q;
                continue;
            }
            if (runs[q].x0 > runs[r].x1) {
                ++r;
                continue;
            }
            const int a = findRoot(parent, static_cast<int>(q));
            const int b = findRoot(parent, static_cast<int>(r));
            if (a != b)
                parent[static_cast<std::size_t>(std::max(a, b))] = std::min(a, b);
            // The run ending first cannot touch a later run of the other row.
            if (runs[q].x1 < runs[r].x1)
                ++q;
            else
                ++r;
        }
        prevBegin = begin;
        prevEnd = end;
    }
    // Components are numbered as OpenCV's block-based labelling numbers them: by the first
    // 2 x 2 block (block row, then block column) holding one of their pixels. Two components
    // never share a block (its pixels are 8-connected).
    struct Component {
        long long firstBlock;
        int left, top, right, bottom, area;
    };
    std::vector<int> component(runs.size(), -1);
    std::vector<Component> comps;
    const long long blockCols = mask.cols / 2 + 1;
    for (std::size_t i = 0; i < runs.size(); ++i) {
        const int root = findRoot(parent, static_cast<int>(i));
        int& c = component[static_cast<std::size_t>(root)];
        const Run& run = runs[i];
        const long long block = (run.y / 2) * blockCols + run.x0 / 2;
        if (c < 0) {
            c = static_cast<int>(comps.size());
            comps.push_back({block, run.x0, run.y, run.x1 - 1, run.y, 0});
        }
        Component& k = comps[static_cast<std::size_t>(c)];
        k.firstBlock = std::min(k.firstBlock, block);
        k.left = std::min(k.left, run.x0);
        k.right = std::max(k.right, run.x1 - 1);
        k.bottom = std::max(k.bottom, run.y);
        k.area += run.x1 - run.x0;
        component[i] = c;
    }
    std::vector<int> order(comps.size());
    for (std::size_t c = 0; c < comps.size(); ++c)
        order[c] = static_cast<int>(c);
    std::sort(order.begin(), order.end(), [&](int a, int b) {
        return comps[static_cast<std::size_t>(a)].firstBlock <
               comps[static_cast<std::size_t>(b)].firstBlock;
    });
    std::vector<int> labelOf(comps.size());
    const int n = static_cast<int>(comps.size()) + 1;
    stats.create(n, cv::CC_STAT_MAX, CV_32S);
    long long setPx = 0;
    for (std::size_t l = 0; l < order.size(); ++l) {
        const Component& k = comps[static_cast<std::size_t>(order[l])];
        labelOf[static_cast<std::size_t>(order[l])] = static_cast<int>(l) + 1;
        int* row = stats.ptr<int>(static_cast<int>(l) + 1);
        row[cv::CC_STAT_LEFT] = k.left;
        row[cv::CC_STAT_TOP] = k.top;
        row[cv::CC_STAT_WIDTH] = k.right - k.left + 1;
        row[cv::CC_STAT_HEIGHT] = k.bottom - k.top + 1;
        row[cv::CC_STAT_AREA] = k.area;
        setPx += k.area;
    }
    int* background = stats.ptr<int>(0);
    background[cv::CC_STAT_LEFT] = 0;
    background[cv::CC_STAT_TOP] = 0;
    background[cv::CC_STAT_WIDTH] = mask.cols;
    background[cv::CC_STAT_HEIGHT] = mask.rows;
    background[cv::CC_STAT_AREA] = static_cast<int>(static_cast<long long>(mask.total()) - setPx);
    labels = cv::Mat::zeros(mask.size(), CV_32S);
    for (std::size_t i = 0; i < runs.size(); ++i) {
        const Run& run = runs[i];
        std::int32_t* row = labels.ptr<std::int32_t>(run.y);
        std::fill(row + run.x0, row + run.x1, labelOf[static_cast<std::size_t>(component[i])]);
    }
    return n;
}

} // namespace slicestation::pipeline
