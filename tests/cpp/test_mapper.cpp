#include <gtest/gtest.h>
// placeholder: tests for mapper (being written)
