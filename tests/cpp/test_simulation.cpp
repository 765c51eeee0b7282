#include <gtest/gtest.h>
// placeholder: tests for simulation (being written)
