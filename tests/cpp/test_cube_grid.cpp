#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/cube_grid.hpp>

#include <Eigen/Geometry>

#include <cmath>

namespace terracube {
namespace {

TEST(CubeGrid, IndexFollowsEquation1AndEquations7To9InvertIt) {
  // [CBC] eq. (1): I = ix + iy ixmax + iz ixmax iymax; eqs. (7)-(9) recover (ix, iy, iz).
  CubeGrid grid;
  grid.edge_m = 0.5;
  grid.ixmax = 7;
  grid.iymax = 5;
  grid.izmax = 3;
  EXPECT_EQ(grid.index(0, 0, 0), 0);
  EXPECT_EQ(grid.index(6, 0, 0), 6);
  EXPECT_EQ(grid.index(0, 1, 0), 7);
  EXPECT_EQ(grid.index(0, 0, 1), 35);
  EXPECT_EQ(grid.index(3, 2, 1), 3 + 2 * 7 + 1 * 35);
  for (std::int64_t index = 0; index < grid.num_cubes(); ++index) {
    const CubeCoordinates c = grid.coordinates(index);
    EXPECT_EQ(grid.index(c.x(), c.y(), c.z()), index);
  }
}

TEST(CubeGrid, QuantizeRoundsHalfUpFromTheMinimumAsEquations4To6) {
  // The bounding-box minimum is the centre of cube 0: [-E/2, E/2) maps to 0.
  EXPECT_EQ(quantize(1.0, 1.0, 2.0), 0);
  EXPECT_EQ(quantize(1.24, 1.0, 2.0), 0);
  EXPECT_EQ(quantize(1.25, 1.0, 2.0), 1);  // exactly half a cube: rounds up
  EXPECT_EQ(quantize(1.74, 1.0, 2.0), 1);
  EXPECT_EQ(quantize(1.75, 1.0, 2.0), 2);
}

TEST(CubeGrid, CollapseReportsGeometryOfEquations2And3) {
  // [CBC] eqs. (2)-(3) give ixmax and iymax; izmax is ours, by the same rule.
  // x spans 0..2.3 at E = 0.5: round(4.6) + 1 = 6 cubes; y spans 0..0.2: round(0.4) + 1 = 1;
  // z spans -1..0.26: round(2.52) + 1 = 4.
  const std::vector<Eigen::Vector3d> points = {{0.0, 0.0, -1.0}, {2.3, 0.2, 0.26}};
  CollapseParams params;
  params.edge_m = 0.5;
  const CollapseResult result = collapse_overhangs(points, params);
  EXPECT_EQ(result.grid.ixmax, 6);
  EXPECT_EQ(result.grid.iymax, 1);
  EXPECT_EQ(result.grid.izmax, 4);
  EXPECT_DOUBLE_EQ(result.grid.min_corner.z(), -1.0);
  ASSERT_EQ(result.occupied_cubes.size(), 2U);
  EXPECT_EQ(result.occupied_cubes[0], 0);
  EXPECT_EQ(result.occupied_cubes[1], result.grid.index(5, 0, 3));
  EXPECT_TRUE(result.grid.center(result.occupied_cubes[1]).isApprox(Eigen::Vector3d(2.5, 0.0, 0.5)));
}

TEST(CubeGrid, SigmaFromRobotHeightIsCeiling) {
  EXPECT_EQ(sigma_from_robot_height(0.7, 0.5), 2);
  EXPECT_EQ(sigma_from_robot_height(1.0, 0.5), 2);
  EXPECT_EQ(sigma_from_robot_height(1.01, 0.5), 3);
  EXPECT_EQ(sigma_from_robot_height(0.1, 0.5), 1);
  EXPECT_EQ(sigma_from_robot_height(0.9, 0.5), 2);  // [CBC] section IV-B: ceil(0.9 m / 0.5 m) = 2
}

TEST(CubeGrid, SigmaIsExactForDecimalLengths) {
  // In binary 2.1 / 0.3 = 7.000000000000001 and 2.7 / 0.3 = 9.000000000000002; a plain ceil gives
  // 8 and 10. Decimal lengths that divide evenly give the whole number.
  EXPECT_EQ(sigma_from_robot_height(2.1, 0.3), 7);
  EXPECT_EQ(sigma_from_robot_height(2.1, 0.7), 3);
  EXPECT_EQ(sigma_from_robot_height(2.7, 0.3), 9);
  EXPECT_EQ(sigma_from_robot_height(0.3, 0.1), 3);
  EXPECT_EQ(sigma_from_robot_height(0.7, 0.1), 7);
  EXPECT_EQ(sigma_from_robot_height(2.1000001, 0.3), 8) << "just above a whole number still rounds up";
  EXPECT_EQ(sigma_from_robot_height(2.0999999, 0.3), 7);
  EXPECT_THROW(sigma_from_robot_height(0.0, 0.5), std::invalid_argument);
  EXPECT_THROW(sigma_from_robot_height(1.0, -0.5), std::invalid_argument);
  EXPECT_THROW(sigma_from_robot_height(NAN, 0.5), std::invalid_argument);
}

TEST(CubeGrid, LevelingTransformIsRyPitchTimesRxRoll) {
  const double roll = 0.1;
  const double pitch = -0.2;
  const Eigen::Matrix4d level = leveling_transform(roll, pitch);
  Eigen::Matrix3d rx;
  rx << 1, 0, 0, 0, std::cos(roll), -std::sin(roll), 0, std::sin(roll), std::cos(roll);
  Eigen::Matrix3d ry;
  ry << std::cos(pitch), 0, std::sin(pitch), 0, 1, 0, -std::sin(pitch), 0, std::cos(pitch);
  EXPECT_TRUE((level.topLeftCorner<3, 3>().isApprox(ry * rx, 1e-12)));
  EXPECT_TRUE((level.topRightCorner<3, 1>().isZero(0.0)));
  EXPECT_TRUE(level.row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1)));
  EXPECT_THROW(leveling_transform(NAN, 0.0), std::invalid_argument);
}

TEST(CubeGrid, AttitudeFromGravityIsTheLevelingThatTurnsUpOntoZ) {
  // An accelerometer at rest on a sensor with attitude (roll, pitch, any yaw) reads g R^T e_z.
  for (const double roll : {0.0, 0.3, -1.2, 2.5}) {
    for (const double pitch : {0.0, -0.4, 1.1}) {
      const Eigen::Matrix3d world_sensor = Eigen::AngleAxisd(0.7, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
                                           leveling_transform(roll, pitch).topLeftCorner<3, 3>();
      const Eigen::Vector3d reading = 9.81 * world_sensor.transpose() * Eigen::Vector3d::UnitZ();
      const Attitude attitude = attitude_from_gravity(reading);
      EXPECT_NEAR(attitude.roll_rad, roll, 1e-12);
      EXPECT_NEAR(attitude.pitch_rad, pitch, 1e-12);
      const Eigen::Vector3d leveled =
          leveling_transform(attitude.roll_rad, attitude.pitch_rad).topLeftCorner<3, 3>() * reading;
      EXPECT_TRUE(leveled.isApprox(9.81 * Eigen::Vector3d::UnitZ(), 1e-12));
    }
  }
  EXPECT_THROW(attitude_from_gravity(Eigen::Vector3d::Zero()), std::invalid_argument);
  EXPECT_THROW(attitude_from_gravity(Eigen::Vector3d(0.0, NAN, 9.8)), std::invalid_argument);
}

}  // namespace
}  // namespace terracube
