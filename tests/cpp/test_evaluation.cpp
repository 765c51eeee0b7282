#include <gtest/gtest.h>
// placeholder: tests for evaluation (being written)
