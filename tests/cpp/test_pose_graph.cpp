#include <gtest/gtest.h>
// placeholder: tests for pose_graph (being written)
