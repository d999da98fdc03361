// The alert centre alone (Notifier over a journal on a temporary directory): every alert is
// stored first, then handed to every channel and listener; a full disk holds it, not loses it.
#include "../../common/test_dir.hpp"
#include "full_disk_vfs.hpp"
#include "slicestation/daemon/alerts/notifier.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <string>
#include <vector>

using namespace slicestation;
using namespace slicestation::daemon;

namespace {

class NotifierTest : public ::testing::Test {
protected:
    void SetUp() override {
        testing_vfs::FullDiskVfs::install(); // before the journal opens: it opens through it
        dir_ = testing_dir::freshTestDir("notifier");
        journal_ = Journal::open(dir_ / "journal.sqlite").value();
        notifier_ = std::make_unique<Notifier>(*journal_);
        notifier_->addChannel([this](const AlertRecord& a) { delivered_.push_back(a); });
        notifier_->addListener([this](const StationEvent& e) { events_.push_back(e.type); });
    }
    void TearDown() override {
        testing_vfs::FullDiskVfs::install().setFull(false);
        notifier_.reset();
        journal_.reset();
        std::filesystem::remove_all(dir_);
    }
    std::filesystem::path dir_;
    std::unique_ptr<Journal> journal_;
    std::unique_ptr<Notifier> notifier_;
    std::vector<AlertRecord> delivered_;
    std::vector<std::string> events_;
};

TEST_F(NotifierTest, AnAlertIsStoredThenDeliveredAndTold) {
    auto id = notifier_->raise(AlertKind::CameraFault, AlertSeverity::Critical, "capture timed out",
                               std::nullopt, std::nullopt);
    ASSERT_TRUE(id);
    auto stored = journal_->alert(*id);
    ASSERT_TRUE(stored);
    EXPECT_EQ(stored->kind, AlertKind::CameraFault);
    ASSERT_EQ(delivered_.size(), 1u);
    EXPECT_EQ(delivered_[0].id, *id) << "channels get the stored alert, with its id";
    EXPECT_EQ(events_, std::vector<std::string>{"alert_raised"});

    auto acked = notifier_->acknowledge(*id, "accept");
    ASSERT_TRUE(acked);
    EXPECT_TRUE(acked->acknowledgedUtc);
    EXPECT_EQ(events_.back(), "alert_acknowledged");
    EXPECT_FALSE(notifier_->acknowledge(*id, "accept")) << "acknowledged once";
    EXPECT_EQ(notifier_->acknowledge(424242, "accept").error().code, core::ErrorCode::NotFound);
}

TEST_F(NotifierTest, EveryEndOfARunRaisesItsAlert) {
    PlannedSection p;
    p.slideName = "slide-1";
    p.name = "s1";
    auto run = journal_->createRun("r", nlohmann::json::object(), nlohmann::json::object(), {p});
    ASSERT_TRUE(run);
    ASSERT_TRUE(notifier_->runStateChanged(*run, RunState::Paused, "stage_fault: x drive alarm"));
    ASSERT_EQ(delivered_.size(), 1u);
    EXPECT_EQ(delivered_[0].kind, AlertKind::RunPaused);
    EXPECT_EQ(delivered_[0].severity, AlertSeverity::Warning);
    EXPECT_NE(delivered_[0].message.find("stage_fault: x drive alarm"), std::string::npos);
    EXPECT_EQ(events_.front(), "run_state");
    ASSERT_TRUE(notifier_->runStateChanged(*run, RunState::Running, ""));
    EXPECT_EQ(delivered_.size(), 1u) << "running is no alert";
}

TEST_F(NotifierTest, AFullDiskHoldsTheAlertAndStoresItLater) {
    testing_vfs::FullDiskVfs::install().setFull(true);
    auto id = notifier_->raise(AlertKind::LowDisk, AlertSeverity::Critical, "no space",
                               std::nullopt, std::nullopt);
    EXPECT_FALSE(id) << "the journal refused it";
    ASSERT_EQ(delivered_.size(), 1u) << "delivered all the same";
    EXPECT_LT(delivered_[0].id, 0) << "a held alert has a negative id";
    (void)notifier_->raise(AlertKind::LowDisk, AlertSeverity::Critical, "no space", std::nullopt,
                           std::nullopt);
    EXPECT_EQ(notifier_->heldAlerts().size(), 1u) << "the same alert is not held twice";
    EXPECT_EQ(delivered_.size(), 1u);
    EXPECT_EQ(notifier_->storeHeldAlerts(), 1u) << "still full";

    testing_vfs::FullDiskVfs::install().setFull(false);
    EXPECT_EQ(notifier_->storeHeldAlerts(), 0u);
    auto open = journal_->alerts(true);
    ASSERT_TRUE(open);
    ASSERT_EQ(open->size(), 1u);
    EXPECT_EQ(open->front().kind, AlertKind::LowDisk);
    EXPECT_EQ(events_.back(), "alert_stored");
}

} // namespace
