#include "core/volume/regions.h"

#include <gtest/gtest.h>

namespace decima {
namespace {

RegionTable Table(const std::vector<double>& means, bool hu,
                  const std::vector<std::string>& names = {}) {
  RegionTable t;
  EXPECT_TRUE(MakeRegionTable(means, std::vector<int64_t>(means.size(), 10), hu, names, &t).ok());
  return t;
}

TEST(RegionsTest, HounsfieldMeansGetAirSoftTissueBone) {
  // A head CT's three classes, labels not in mean order: the names follow the means.
  const RegionTable t = Table({35, -990, 720}, true);
  EXPECT_EQ(t.naming, "ct-hu");
  EXPECT_EQ(t.regions[0].name, "soft tissue");
  EXPECT_EQ(t.regions[1].name, "air");
  EXPECT_EQ(t.regions[2].name, "bone");
  EXPECT_FALSE(t.regions[1].in_seg);  // air is not a SEG segment
  EXPECT_TRUE(t.regions[0].in_seg);
  EXPECT_EQ(t.regions[0].type.value, "87784001");
  EXPECT_EQ(t.regions[2].type.value, "3138006");
  EXPECT_EQ(t.regions[2].category.meaning, "Tissue");
  // Colours: Okabe-Ito, distinct, bone yellow.
  EXPECT_EQ(t.regions[2].rgb, kOkabeIto[3]);
  EXPECT_NE(t.regions[0].rgb, t.regions[1].rgb);
  EXPECT_NE(t.regions[0].rgb, t.regions[2].rgb);
}

// The shared CT head stores HU + 1024 with RescaleIntercept 0: air near 0.
TEST(RegionsTest, ACtWithoutNegativeValuesIsReadWithTheUsualOffset) {
  EXPECT_EQ(HuOffset(0), -1024);
  EXPECT_EQ(HuOffset(-1024), 0);
  RegionTable t;
  ASSERT_TRUE(MakeRegionTable({40, 1060, 1900}, {1, 1, 1}, true, {}, &t, HuOffset(0)).ok());
  EXPECT_EQ(t.regions[0].name, "air");
  EXPECT_EQ(t.regions[1].name, "soft tissue");
  EXPECT_EQ(t.regions[2].name, "bone");
  EXPECT_DOUBLE_EQ(t.regions[1].mean_hu, 36);
}

TEST(RegionsTest, ThresholdsAreWhereDocumented) {
  const RegionTable t = Table({kAirBelowHu - 1, kAirBelowHu, kBoneFromHu - 1, kBoneFromHu}, true);
  EXPECT_EQ(t.regions[0].name, "air");
  EXPECT_EQ(t.regions[1].name, "soft tissue 1");
  EXPECT_EQ(t.regions[2].name, "soft tissue 2");
  EXPECT_EQ(t.regions[3].name, "bone");
  EXPECT_NE(t.regions[1].rgb, t.regions[2].rgb);
}

TEST(RegionsTest, NonCtGetsNeutralOrderedNames) {
  const RegionTable t = Table({300, 20, 900}, false);
  EXPECT_EQ(t.naming, "intensity");
  EXPECT_EQ(t.regions[1].name, "region 1 (darkest)");
  EXPECT_EQ(t.regions[0].name, "region 2");
  EXPECT_EQ(t.regions[2].name, "region 3 (brightest)");
  for (const RegionInfo& r : t.regions) {
    EXPECT_TRUE(r.in_seg);
    EXPECT_EQ(r.type.meaning, "Tissue");
  }
}

TEST(RegionsTest, UserNamesWinButCodesFollowIntensity) {
  const RegionTable t = Table({-1000, 40, 800}, true, {"outside", "brain", "skull"});
  EXPECT_EQ(t.naming, "user");
  EXPECT_EQ(t.regions[1].name, "brain");
  EXPECT_EQ(t.regions[1].type.meaning, "Soft tissue");
  EXPECT_FALSE(t.regions[0].in_seg);
}

TEST(RegionsTest, PlausiblyHu) {
  EXPECT_TRUE(PlausiblyHu("CT", 0, 255));
  EXPECT_FALSE(PlausiblyHu("MR", -1024, 3000));
  EXPECT_TRUE(PlausiblyHu("", -1024, 3071));
  EXPECT_FALSE(PlausiblyHu("", 0, 4095));  // an MR, or a CT stored without its rescale
  EXPECT_FALSE(PlausiblyHu("", -1024, 65000));
}

TEST(RegionsTest, ValidateRegionNamesRefusesBadNames) {
  int index = 99;
  EXPECT_TRUE(ValidateRegionNames({"air", "brain", "bone"}, 3, &index).ok());
  EXPECT_FALSE(ValidateRegionNames({"air", "brain"}, 3, &index).ok());
  EXPECT_EQ(index, -1);
  EXPECT_FALSE(ValidateRegionNames({"air", "", "bone"}, 3, &index).ok());
  EXPECT_EQ(index, 1);
  EXPECT_FALSE(ValidateRegionNames({"air", "  ", "bone"}, 3, &index).ok());
  EXPECT_EQ(index, 1);
  EXPECT_FALSE(ValidateRegionNames({"air", "brain", "Air"}, 3, &index).ok());
  EXPECT_EQ(index, 2);
  EXPECT_FALSE(ValidateRegionNames({"air", "br\tain", "bone"}, 3, &index).ok());
  EXPECT_EQ(index, 1);
  EXPECT_FALSE(ValidateRegionNames({"air", "bra\x7fin", "bone"}, 3, &index).ok());
  EXPECT_FALSE(ValidateRegionNames({"air", "b\xC2\x85", "bone"}, 3, &index).ok());  // NEL
  EXPECT_FALSE(ValidateRegionNames({"air", "a\\b", "bone"}, 3, &index).ok());
  EXPECT_FALSE(ValidateRegionNames({"air", "\xff", "bone"}, 3, &index).ok());
  EXPECT_FALSE(ValidateRegionNames({"air", std::string(65, 'x'), "bone"}, 3, &index).ok());
  EXPECT_TRUE(ValidateRegionNames({"air", std::string(64, 'x'), "Gehirn \xC3\xBC"}, 3).ok());
}

TEST(RegionsTest, SurfaceFileNamesAreSafeAndUnique) {
  const RegionTable t = Table({0, 1, 2, 3}, false, {"Soft tissue", "soft/tissue", "../..", "x"});
  EXPECT_EQ(SurfaceFileNames(t),
            (std::vector<std::string>{"surface-soft_tissue.stl", "surface-soft_tissue_2.stl",
                                      "surface-region_3.stl", "surface-x.stl"}));
}

}  // namespace
}  // namespace decima
