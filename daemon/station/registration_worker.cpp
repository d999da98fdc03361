#include "slicestation/daemon/station/registration_worker.hpp"

#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/core/image_file.hpp"

#include <algorithm>
#include <cstdlib>
#include <map>
#include <exception>

namespace slicestation::daemon {

RegistrationWorker::RegistrationWorker(Journal& journal, Notifier& notifier, const AtlasStack& stack,
                                       std::filesystem::path stateDir, PhaseStats& stats)
    : journal_(journal), notifier_(notifier), stack_(stack), stateDir_(std::move(stateDir)),
      stats_(stats) {}

RegistrationWorker::~RegistrationWorker() { stop(); }

void RegistrationWorker::start() {
    std::lock_guard lock(mutex_);
    if (thread_.joinable()) return;
    stopping_ = false;
    thread_ = std::thread([this] { loop(); });
}

void RegistrationWorker::enqueue(std::int64_t captureId) {
    {
        std::lock_guard lock(mutex_);
        queue_.push_back(captureId);
    }
    cv_.notify_all();
}

bool RegistrationWorker::idle() const {
    std::lock_guard lock(mutex_);
    return queue_.empty() && !busy_;
}

bool RegistrationWorker::waitIdle(std::chrono::milliseconds timeout) const {
    std::unique_lock lock(mutex_);
    return cv_.wait_for(lock, timeout, [this] { return queue_.empty() && !busy_; });
}

void RegistrationWorker::stop() noexcept {
    {
        std::lock_guard lock(mutex_);
        stopping_ = true;
        queue_.clear();
    }
    cv_.notify_all();
    if (thread_.joinable()) thread_.join();
}

void RegistrationWorker::loop() {
    for (;;) {
        std::int64_t id = 0;
        {
            std::unique_lock lock(mutex_);
            cv_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
            if (stopping_) return;
            id = queue_.front();
            queue_.pop_front();
            busy_ = true;
        }
        try {
            process(id);
        } catch (const std::exception& e) {
            // Nothing may escape a thread entry; a library bug becomes a failed section.
            if (auto c = journal_.capture(id)) {
                (void)journal_.failSection(c->sectionId, std::string("registration crashed: ") + e.what());
                (void)notifier_.raise("registration_failed", "warning",
                                      std::string("registration crashed: ") + e.what(), std::nullopt,
                                      c->sectionId);
            }
        }
        {
            std::lock_guard lock(mutex_);
            busy_ = false;
        }
        cv_.notify_all();
    }
}

core::Result<int> RegistrationWorker::matchToStack(const std::filesystem::path& image, double umPerPx,
                                                  std::optional<int> expected, int window) {
    // The stack's matching features are computed once and kept: they do not change.
    if (features_.empty()) {
        auto f = stackFeatures(stack_);
        if (!f) return f.error();
        features_ = std::move(*f);
        if (features_.empty()) return core::makeError(core::ErrorCode::InvalidArgument, "empty atlas stack");
    }
    auto img = core::readImage(image);
    if (!img) return img.error();
    pipeline::MatchOptions opt;
    if (expected) {
        opt.first = std::max(0, *expected - window);
        opt.last = std::min(static_cast<int>(features_.size()) - 1, *expected + window);
    }
    auto section = pipeline::sectionFeatures(*img, umPerPx, features_.front().workUmPerPx);
    if (!section) return section.error();
    auto m = pipeline::matchSection(*section, features_, opt);
    if (!m) return m.error();
    return m->index;
}

void RegistrationWorker::process(std::int64_t captureId) {
    PhaseTimer timer(stats_, "register");
    auto capture = journal_.capture(captureId);
    if (!capture) return;
    auto section = journal_.section(capture->sectionId);
    if (!section || section->state != SectionState::Captured) return; // a rescan overtook it
    auto run = journal_.run(section->runId);
    if (!run) return;
    const std::string label = "section " + section->name + " (" + section->slideName + ", run " +
                              std::to_string(run->id) + ")";
    auto fail = [&](const std::string& why) {
        (void)journal_.failSection(section->id, why);
        (void)notifier_.raise("registration_failed", "warning", label + ": " + why, run->id, section->id);
        notifier_.publish({"section_failed", {{"section_id", section->id}, {"reason", why}}});
    };
    auto settings = scanSettingsFromJson(run->settings, "run " + std::to_string(run->id) + " settings");
    if (!settings) return fail(settings.error().message);

    const std::filesystem::path image = stateDir_ / capture->imagePath;
    const std::filesystem::path base =
        image.parent_path() / (image.filename().string().substr(0, image.filename().string().find('.')));
    const auto rel = [&](const std::filesystem::path& p) {
        return std::filesystem::relative(p, stateDir_).string();
    };

    RegistrationRecord rec;
    rec.captureId = captureId;
    std::optional<int> slice = section->expectedSlice;
    std::string warning;
    if (settings->checkAtlasMatch || !slice) {
        PhaseTimer matchTimer(stats_, "atlas_match");
        // The whole stack is searched: a section mounted far out of order must show where it belongs.
        auto m = matchToStack(image, capture->umPerPx, std::nullopt, 0);
        if (m) {
            rec.matchedSlice = *m;
            if (!slice) {
                slice = rec.matchedSlice;
            } else if (std::abs(*rec.matchedSlice - *slice) > settings->mismatchToleranceSlices) {
                warning = "the section matches atlas slice " + std::to_string(*rec.matchedSlice) +
                          ", not the planned " + std::to_string(*slice) +
                          " (mounted out of order?); registered to the planned slice";
            }
        } else if (!slice) {
            return fail("no atlas slice planned and matching failed: " + m.error().message);
        }
    }
    rec.atlasSlice = *slice;

    RegisterRequest rq;
    rq.atlas = stack_.dir;
    rq.image = image;
    rq.imageUmPerPx = capture->umPerPx;
    rq.output = base.string() + ".result.json";
    rq.overlay = base.string() + ".overlay.png";
    rq.warpedLabels = base.string() + ".labels.tif";
    if (auto u = useStackSlice(rq, *slice); !u) return fail(u.error().message);
    auto result = runRegister(rq);
    if (!result) return fail("registration failed: " + result.error().message);

    rec.damaged = result->value("damaged", false);
    rec.damageFraction = result->value("damage_fraction", 0.0);
    rec.summary = result->value("damage_summary", std::string());
    rec.warning = warning;
    if (result->contains("quality")) rec.quality = (*result)["quality"].value("tissue_overlap", 0.0);
    rec.resultPath = rel(rq.output);
    rec.overlayPath = rel(*rq.overlay);
    rec.labelsPath = rel(*rq.warpedLabels);
    rec.result = *result;
    // The atlas regions the section shows, named from the stack's ontology, largest first.
    if (auto labels = core::readImage(*rq.warpedLabels); labels && labels->type() == CV_32SC1) {
        std::map<std::int32_t, std::int64_t> counts;
        std::int64_t inside = 0;
        for (int y = 0; y < labels->rows; ++y) {
            const auto* row = labels->ptr<std::int32_t>(y);
            for (int x = 0; x < labels->cols; ++x)
                if (row[x] > 0) {
                    ++counts[row[x]];
                    ++inside;
                }
        }
        std::vector<std::pair<std::int64_t, std::int32_t>> order;
        for (const auto& [regionId, n] : counts) order.push_back({n, regionId});
        std::sort(order.rbegin(), order.rend());
        nlohmann::json regions = nlohmann::json::array();
        for (const auto& [n, regionId] : order) {
            nlohmann::json r{{"id", regionId}, {"share", inside > 0 ? static_cast<double>(n) / inside : 0.0}};
            if (const StackRegion* sr = findRegion(stack_, static_cast<std::uint32_t>(regionId))) {
                r["name"] = sr->name;
                r["acronym"] = sr->acronym;
                r["color"] = colorHex(sr->colorRgb);
            }
            regions.push_back(std::move(r));
        }
        rec.result["regions"] = std::move(regions);
    }
    auto id = journal_.recordRegistration(rec);
    if (!id) {
        (void)notifier_.raise("journal_error", "critical", label + ": cannot store registration: " +
                                                               id.error().message, run->id, section->id);
        return;
    }
    rec.id = *id;
    nlohmann::json ev = toJson(rec);
    ev["section_id"] = section->id;
    ev["run_id"] = run->id;
    notifier_.publish({rec.damaged ? "section_damaged" : "section_registered", ev});
    if (!warning.empty())
        (void)notifier_.raise("atlas_mismatch", "warning", label + ": " + warning, run->id, section->id);
    if (rec.damaged)
        (void)notifier_.raise("damaged", "critical",
                              label + " is damaged (" + rec.summary +
                                  "): re-mount it and request a rescan, or accept it as is",
                              run->id, section->id);
}

} // namespace slicestation::daemon
