// The station's verdict on a registration (issue 18): the run's flag score applied to the
// pipeline's score, the pipeline's "check the registration" kept, and the alert texts with the
// score. Registrations are built by hand: the pipeline does not produce check_registration yet.
#include "slicestation/daemon/station/registration_worker.hpp"

#include <gtest/gtest.h>

using namespace slicestation;
using namespace slicestation::daemon;

namespace {

pipeline::Registration registration(double score, pipeline::DamageVerdict verdict) {
    pipeline::Registration r;
    r.damageScore = score;
    r.damageVerdict = verdict;
    r.damaged = verdict == pipeline::DamageVerdict::Damaged;
    return r;
}

} // namespace

TEST(DamageVerdict, TheStationsFlagScoreDecidesDamagedOrClean) {
    RegistrationRecord rec;
    // The pipeline (at its 0.5) says damaged; a station at 0.7 does not flag 0.6.
    RegistrationWorker::applyFlagScore(rec, registration(0.6, pipeline::DamageVerdict::Damaged),
                                       0.7);
    EXPECT_EQ(rec.damageVerdict, "clean");
    EXPECT_FALSE(rec.damaged);
    EXPECT_DOUBLE_EQ(*rec.damageScore, 0.6);
    EXPECT_DOUBLE_EQ(*rec.flagScore, 0.7);
    // The pipeline says clean; a station at 0.3 flags 0.4; the threshold itself flags.
    RegistrationWorker::applyFlagScore(rec, registration(0.4, pipeline::DamageVerdict::Clean), 0.3);
    EXPECT_EQ(rec.damageVerdict, "damaged");
    EXPECT_TRUE(rec.damaged);
    RegistrationWorker::applyFlagScore(rec, registration(0.5, pipeline::DamageVerdict::Clean), 0.5);
    EXPECT_TRUE(rec.damaged);
    // "Check the registration" stays a third state, whatever the score and threshold.
    for (const double flag : {0.1, 0.5, 0.9}) {
        RegistrationWorker::applyFlagScore(
            rec, registration(0.62, pipeline::DamageVerdict::CheckRegistration), flag);
        EXPECT_EQ(rec.damageVerdict, "check_registration") << flag;
        EXPECT_FALSE(rec.damaged) << flag;
    }
}

TEST(DamageVerdict, AlertTextsCarryTheScoreAndTheirOwnWording) {
    RegistrationRecord rec;
    rec.summary = "1 tear (3.1% of the tissue)";
    RegistrationWorker::applyFlagScore(rec, registration(0.8312, pipeline::DamageVerdict::Damaged),
                                       0.5);
    EXPECT_EQ(RegistrationWorker::damageAlertText(rec, "section s05 (slide-01, run 4)"),
              "section s05 (slide-01, run 4) is damaged, score 0.83: 1 tear (3.1% of the tissue): "
              "re-mount it and request a rescan, or accept it as is");
    RegistrationWorker::applyFlagScore(
        rec, registration(0.62, pipeline::DamageVerdict::CheckRegistration), 0.5);
    const std::string check = RegistrationWorker::damageAlertText(rec, "section s05");
    EXPECT_EQ(check.rfind("check the registration of section s05: tissue looks missing where the "
                          "atlas fit is uncertain (score 0.62",
                          0),
              0u)
        << check;
}
