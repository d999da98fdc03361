#include "slicestation/pipeline/series_model.hpp"

#include <algorithm>
#include <cmath>
#include <string>

namespace slicestation::pipeline {
namespace {

using core::ErrorCode;
using core::makeError;

double median(std::vector<double> v) {
    if (v.empty())
        return 0;
    const size_t h = v.size() / 2;
    std::nth_element(v.begin(), v.begin() + long(h), v.end());
    if (v.size() % 2 == 1)
        return v[h];
    const double hi = v[h];
    return 0.5 * (hi + *std::max_element(v.begin(), v.begin() + long(h)));
}

/// Weighted median of (value, weight) pairs.
double weightedMedian(std::vector<std::pair<double, double>> v) {
    if (v.empty())
        return 0;
    std::sort(v.begin(), v.end());
    double total = 0;
    for (const auto& [x, w] : v)
        total += w;
    double run = 0;
    for (const auto& [x, w] : v) {
        run += w;
        if (run >= 0.5 * total)
            return x;
    }
    return v.back().first;
}

struct Line {
    double a = 0, s = 0;
    double positionOf(int slot) const { return a + s * slot; }
};

/// Slots in arrival order: a section takes the slot after the last on-line section's when it
/// lies within `tau` of it (the run continues regularly), else the nearest slot.
std::vector<int> assignSlots(const std::vector<SeriesObservation>& obs, const Line& l, double tau) {
    std::vector<int> slots(obs.size());
    bool havePrev = false;
    int prev = 0;
    for (size_t k = 0; k < obs.size(); ++k) {
        const double t = (obs[k].positionUm - l.a) / l.s;
        int slot = int(std::lround(t));
        if (havePrev && std::abs(obs[k].positionUm - (l.a + l.s * (prev + 1))) <= tau)
            slot = prev + 1;
        slots[k] = slot;
        if (std::abs(obs[k].positionUm - (l.a + l.s * slot)) <= tau) {
            prev = slot;
            havePrev = true;
        }
    }
    return slots;
}

/// Robust cost of a line, in units of tau^2 per section: the truncated squared residuals, plus
/// half a unit for each step between consecutive sections that is not one slot forward (so a
/// half spacing, which fits everything, pays for the gaps it makes).
double cost(const std::vector<SeriesObservation>& obs, const std::vector<double>& w, const Line& l,
            double tau) {
    const std::vector<int> slots = assignSlots(obs, l, tau);
    double c = 0;
    for (size_t k = 0; k < obs.size(); ++k) {
        const double r = (obs[k].positionUm - (l.a + l.s * slots[k])) / tau;
        c += w[k] * std::min(r * r, 1.0);
        if (k > 0 && slots[k] - slots[k - 1] != 1)
            c += 0.5;
    }
    return c;
}

/// Indices (into `items`) of a longest strictly increasing subsequence of `values`.
std::vector<size_t> longestIncreasing(const std::vector<int>& values) {
    const size_t n = values.size();
    std::vector<size_t> len(n, 1), from(n, n);
    for (size_t i = 0; i < n; ++i)
        for (size_t j = 0; j < i; ++j)
            if (values[j] < values[i] && len[j] + 1 > len[i]) {
                len[i] = len[j] + 1;
                from[i] = j;
            }
    size_t end = 0;
    for (size_t i = 0; i < n; ++i)
        if (len[i] > len[end])
            end = i;
    std::vector<size_t> out;
    for (size_t i = end; i < n; i = from[i])
        out.push_back(i);
    std::reverse(out.begin(), out.end());
    return out;
}

/// Order from the plan: a section whose own match breaks the cutting order (off the line, out
/// of order, a duplicate) with a score under `ratio` x the median score on the line is placed at
/// the free slot between its neighbours in the run (`online[run[...]]`), counted from the one
/// before it as if the run went on regularly. Sections placed earlier bound the later ones, so
/// the placed run stays in order. No free slot between them: left as it was.
void placeWeakContradictions(const std::vector<SeriesObservation>& obs, double ratio,
                             const std::vector<size_t>& online, const std::vector<size_t>& run,
                             SeriesFit& fit) {
    if (ratio <= 0 || run.empty())
        return;
    std::vector<double> scores;
    for (size_t k : online)
        scores.push_back(obs[k].score);
    const double weak = ratio * median(scores);
    const size_t n = obs.size();
    std::vector<bool> fixed(n, false);
    for (size_t r : run)
        fixed[online[r]] = true;
    for (size_t k = 0; k < n; ++k) {
        SeriesSectionFit& s = fit.sections[k];
        const bool contradicts = s.anomaly == SeriesAnomaly::OffLine ||
                                 s.anomaly == SeriesAnomaly::OutOfOrder ||
                                 s.anomaly == SeriesAnomaly::Duplicate;
        if (!contradicts || obs[k].score >= weak)
            continue;
        size_t before = n, after = n;
        for (size_t j = k; j-- > 0;)
            if (fixed[j]) {
                before = j;
                break;
            }
        for (size_t j = k + 1; j < n; ++j)
            if (fixed[j]) {
                after = j;
                break;
            }
        const int lo = before < n ? fit.sections[before].slot + 1 : -(1 << 30);
        const int hi = after < n ? fit.sections[after].slot - 1 : (1 << 30);
        if (lo > hi)
            continue;
        const int want = before < n ? fit.sections[before].slot + int(k - before)
                                    : fit.sections[after].slot - int(after - k);
        if (s.inlier)
            --fit.inliers;
        s.slot = std::clamp(want, lo, hi);
        s.predictedUm = fit.positionOfSlot(s.slot);
        s.residualUm = obs[k].positionUm - s.predictedUm;
        s.inlier = false;
        s.anomaly = SeriesAnomaly::Placed;
        fixed[k] = true;
    }
}

} // namespace

std::string_view toString(SeriesAnomaly anomaly) noexcept {
    switch (anomaly) {
    case SeriesAnomaly::None:
        return "none";
    case SeriesAnomaly::OffLine:
        return "off-line";
    case SeriesAnomaly::Skipped:
        return "skipped-before";
    case SeriesAnomaly::Swapped:
        return "swapped";
    case SeriesAnomaly::OutOfOrder:
        return "out-of-order";
    case SeriesAnomaly::Duplicate:
        return "duplicate";
    case SeriesAnomaly::Placed:
        return "placed-on-line";
    }
    return "unknown";
}

double SeriesFit::predictUm(int index) const {
    // The slot offset (slot - index) of the last five on-line sections before `index`, their
    // median: one section far off (a wrong match that happens to sit on a slot) does not move
    // the prediction, a skip does once it is confirmed by the sections after it.
    std::vector<double> offsets;
    for (int j = std::min(index, int(sections.size())) - 1; j >= 0 && offsets.size() < 5; --j)
        if (sections[size_t(j)].inlier)
            offsets.push_back(double(sections[size_t(j)].slot - j));
    if (offsets.empty())
        return positionOfSlot(double(index));
    std::sort(offsets.begin(), offsets.end());
    return positionOfSlot(double(index) + offsets[(offsets.size() - 1) / 2]);
}

core::Result<SeriesFit> fitSeries(const std::vector<SeriesObservation>& obs,
                                  const SeriesModelOptions& options) {
    if (obs.empty())
        return makeError(ErrorCode::InvalidArgument, "the series has no sections");
    if (!std::isfinite(options.intervalUm) || options.intervalUm < 0)
        return makeError(ErrorCode::InvalidArgument,
                         "the plan's interval must be finite and >= 0 um (0 = unknown)");
    if (!std::isfinite(options.spacingSlack) || options.spacingSlack <= 0 ||
        options.spacingSlack >= 1)
        return makeError(ErrorCode::InvalidArgument, "spacing slack must be in (0, 1)");
    if (!std::isfinite(options.placeScoreRatio) || options.placeScoreRatio < 0)
        return makeError(ErrorCode::InvalidArgument, "place score ratio must be finite and >= 0");
    if (!std::isfinite(options.inlierUm) || options.inlierUm < 0)
        return makeError(ErrorCode::InvalidArgument, "inlier distance must be finite and >= 0");
    std::vector<double> scores;
    for (size_t k = 0; k < obs.size(); ++k) {
        if (!std::isfinite(obs[k].positionUm) || !std::isfinite(obs[k].score) || obs[k].score < 0 ||
            !std::isfinite(obs[k].tiltColumnsDeg) || !std::isfinite(obs[k].tiltRowsDeg))
            return makeError(ErrorCode::InvalidArgument,
                             "section " + std::to_string(k) +
                                 " has a non-finite or negative position, score or tilt");
        scores.push_back(obs[k].score);
    }
    const size_t n = obs.size();
    const double medScore = std::max(median(scores), 1e-12);
    std::vector<double> w(n);
    for (size_t k = 0; k < n; ++k)
        w[k] = std::clamp(obs[k].score / medScore, 0.2, 2.0);
    auto tauOf = [&](double s) {
        return options.inlierUm > 0 ? options.inlierUm : 0.4 * std::abs(s);
    };

    // Without a plan, the spacing prior is the Theil-Sen slope of position against arrival
    // index (the median of the pairwise slopes): the plain "linear in index" reading of the
    // series, which a few wrong matches do not move. Hypotheses then stay within the slack of
    // it, as they would of a plan's interval.
    double prior = options.intervalUm;
    if (prior <= 0 && n >= 4) {
        std::vector<double> slopes;
        for (size_t i = 0; i < n; ++i)
            for (size_t j = i + 1; j < n; ++j)
                slopes.push_back((obs[j].positionUm - obs[i].positionUm) / double(j - i));
        prior = std::abs(median(slopes));
    }

    SeriesFit fit;
    Line best;
    if (n == 1 || (n == 2 && options.intervalUm > 0)) {
        // Too few to fit a spacing: the plan's (or the two sections' own) through the first.
        best.s = options.intervalUm > 0 ? options.intervalUm
                                        : (n == 2 ? obs[1].positionUm - obs[0].positionUm : 0);
        if (n == 2 && options.intervalUm > 0 && obs[1].positionUm < obs[0].positionUm)
            best.s = -best.s;
        best.a = obs[0].positionUm;
    } else {
        // Hypotheses: every pair of sections up to six apart, with no skip or one between.
        double bestCost = 1e300;
        for (size_t i = 0; i < n; ++i)
            for (size_t j = i + 1; j < n && j <= i + 6; ++j)
                for (int extra = 0; extra <= 1; ++extra) {
                    const double d = double(j - i) + extra;
                    Line l;
                    l.s = (obs[j].positionUm - obs[i].positionUm) / d;
                    if (l.s == 0 || !std::isfinite(l.s))
                        continue;
                    if (prior > 0 && std::abs(std::abs(l.s) - prior) > options.spacingSlack * prior)
                        continue;
                    l.a = obs[i].positionUm - l.s * double(i);
                    const double c = cost(obs, w, l, tauOf(l.s));
                    if (c < bestCost) {
                        bestCost = c;
                        best = l;
                    }
                }
        if (best.s == 0) {
            // No pair gives a spacing near the plan's (every match far off): the plan's line
            // through the median of position - index x interval.
            best.s = prior > 0 ? prior : 1;
            std::vector<double> a;
            for (size_t k = 0; k < n; ++k)
                a.push_back(obs[k].positionUm - best.s * double(k));
            best.a = median(a);
        }
        // Iteratively reweighted least squares (Tukey weights) on the slots.
        for (int iter = 0; iter < 8; ++iter) {
            const double tau = tauOf(best.s);
            const std::vector<int> slots = assignSlots(obs, best, tau);
            double sw = 0, st = 0, sp = 0, stt = 0, stp = 0;
            int used = 0, minSlot = 1 << 30, maxSlot = -(1 << 30);
            for (size_t k = 0; k < n; ++k) {
                const double r = (obs[k].positionUm - best.positionOf(slots[k])) / tau;
                if (std::abs(r) >= 1)
                    continue;
                const double wk = w[k] * (1 - r * r) * (1 - r * r);
                const double t = slots[k];
                sw += wk;
                st += wk * t;
                sp += wk * obs[k].positionUm;
                stt += wk * t * t;
                stp += wk * t * obs[k].positionUm;
                ++used;
                minSlot = std::min(minSlot, slots[k]);
                maxSlot = std::max(maxSlot, slots[k]);
            }
            if (used < 2 || maxSlot == minSlot)
                break;
            const double den = sw * stt - st * st;
            if (std::abs(den) < 1e-12)
                break;
            Line next;
            next.s = (sw * stp - st * sp) / den;
            next.a = (sp - next.s * st) / sw;
            if (next.s == 0 || !std::isfinite(next.s))
                break;
            const bool same = std::abs(next.s - best.s) < 1e-6 && std::abs(next.a - best.a) < 1e-6;
            best = next;
            if (same)
                break;
        }
    }

    fit.spacingUm = best.s;
    fit.originUm = best.a;
    const double tau = best.s != 0 ? tauOf(best.s) : 1e300;
    std::vector<int> slots = best.s != 0 ? assignSlots(obs, best, tau) : std::vector<int>(n, 0);
    fit.sections.resize(n);
    // Canonical numbering: the first on-line section keeps its own index as its slot.
    int shift = 0;
    for (size_t k = 0; k < n; ++k)
        if (std::abs(obs[k].positionUm - (best.a + best.s * slots[k])) <= tau) {
            shift = int(k) - slots[k];
            break;
        }
    fit.originUm -= best.s * shift;
    std::vector<double> residuals;
    std::vector<std::pair<double, double>> tiltC, tiltR;
    std::vector<size_t> online;
    std::vector<int> onlineSlots;
    for (size_t k = 0; k < n; ++k) {
        SeriesSectionFit& s = fit.sections[k];
        s.slot = slots[k] + shift;
        s.predictedUm = fit.positionOfSlot(s.slot);
        s.residualUm = obs[k].positionUm - s.predictedUm;
        s.inlier = std::abs(s.residualUm) <= tau;
        if (!s.inlier) {
            s.anomaly = SeriesAnomaly::OffLine;
            continue;
        }
        ++fit.inliers;
        residuals.push_back(std::abs(s.residualUm));
        online.push_back(k);
        onlineSlots.push_back(s.slot);
        if (obs[k].tiltEstimated) {
            tiltC.push_back({obs[k].tiltColumnsDeg, w[k]});
            tiltR.push_back({obs[k].tiltRowsDeg, w[k]});
        }
    }
    fit.sigmaUm = 1.4826 * median(residuals);
    fit.tiltSections = int(tiltC.size());
    fit.tiltColumnsDeg = weightedMedian(tiltC);
    fit.tiltRowsDeg = weightedMedian(tiltR);

    // Order among the on-line sections: the longest run of increasing slots is the cutting
    // order; the rest broke it. Neighbours whose slots are exchanged are a swap.
    // The sections around a swap stay regular: the one before takes the slot before both, or
    // the one after the slot after both. And the pair itself steps back by about a spacing
    // (each lies where the other belongs): a step back of less than half a spacing is nearer
    // to two sections on one place (a wrong match) than to an exchange.
    for (size_t a = 0; a + 1 < online.size(); ++a) {
        const size_t k = online[a], k2 = online[a + 1];
        const int hi = fit.sections[k].slot, lo = fit.sections[k2].slot;
        const bool regularBefore = a > 0 && fit.sections[online[a - 1]].slot == lo - 1;
        const bool regularAfter =
            a + 2 < online.size() && fit.sections[online[a + 2]].slot == hi + 1;
        const bool stepsBack = obs[k2].positionUm - obs[k].positionUm <= -0.5 * std::abs(best.s);
        if (k2 == k + 1 && hi == lo + 1 && (regularBefore || regularAfter) && stepsBack) {
            fit.sections[k].anomaly = SeriesAnomaly::Swapped;
            fit.sections[k2].anomaly = SeriesAnomaly::Swapped;
        }
    }
    const std::vector<size_t> run = longestIncreasing(onlineSlots);
    std::vector<bool> inRun(online.size(), false);
    for (size_t r : run)
        inRun[r] = true;
    for (size_t a = 0; a < online.size(); ++a) {
        SeriesSectionFit& s = fit.sections[online[a]];
        if (inRun[a] || s.anomaly == SeriesAnomaly::Swapped)
            continue;
        const bool dup = std::count(onlineSlots.begin(), onlineSlots.end(), s.slot) > 1;
        s.anomaly = dup ? SeriesAnomaly::Duplicate : SeriesAnomaly::OutOfOrder;
    }
    placeWeakContradictions(obs, options.placeScoreRatio, online, run, fit);
    // Skips: slots between consecutive sections of the run that no section took, beyond the
    // sections between them that are off the line or out of order (which may belong there).
    for (size_t r = 1; r < run.size(); ++r) {
        const size_t k1 = online[run[r - 1]], k2 = online[run[r]];
        const int s1 = fit.sections[k1].slot, s2 = fit.sections[k2].slot;
        // A slot counts as taken only by a section that arrived next to the gap (from one before
        // k1 to one after k2: the partner of a swap); a wrong match far away in the run that
        // happens to sit on the lost slot does not hide the skip.
        int missing = 0;
        for (int slot = s1 + 1; slot < s2; ++slot) {
            bool taken = false;
            for (size_t a = 0; a < online.size(); ++a)
                taken =
                    taken || (onlineSlots[a] == slot && online[a] + 1 >= k1 && online[a] <= k2 + 1);
            for (size_t k = k1 + 1; k < k2; ++k)
                taken = taken || (fit.sections[k].anomaly == SeriesAnomaly::Placed &&
                                  fit.sections[k].slot == slot);
            missing += !taken;
        }
        int elsewhere = 0; // sections between them in arrival order but not in the run
        for (size_t k = k1 + 1; k < k2; ++k)
            elsewhere += fit.sections[k].anomaly == SeriesAnomaly::OffLine ||
                         fit.sections[k].anomaly == SeriesAnomaly::OutOfOrder ||
                         fit.sections[k].anomaly == SeriesAnomaly::Duplicate;
        missing -= elsewhere;
        if (missing > 0 && fit.sections[k2].anomaly == SeriesAnomaly::None) {
            fit.sections[k2].anomaly = SeriesAnomaly::Skipped;
            fit.sections[k2].missingBefore = missing;
        }
    }
    for (size_t k = 0; k < n; ++k)
        fit.sections[k].positionUm = fit.sections[k].anomaly == SeriesAnomaly::Placed
                                         ? fit.sections[k].predictedUm
                                         : obs[k].positionUm;
    return fit;
}

} // namespace slicestation::pipeline
