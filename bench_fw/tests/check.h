// A minimal unit-test harness for the host-side tests (g++): CHECK macros that count failures and
// print file:line of each, one TEST registry, a main that reports "N checks, M failed".
#ifndef BENCH_CHECK_H
#define BENCH_CHECK_H

#include <cmath>
#include <cstdio>
#include <cstring>

namespace check {
struct Test {
  const char *name;
  void (*fn)();
  Test *next;
};
Test *&registry();
int &checks();
int &failures();
struct Register {
  Register(const char *name, void (*fn)()) {
    static Test nodes[256];
    static int used = 0;
    nodes[used] = Test{name, fn, registry()};
    registry() = &nodes[used++];
  }
};
}  // namespace check

#define TEST(name)                                              \
  static void test_##name();                                    \
  static check::Register reg_##name(#name, test_##name);        \
  static void test_##name()

#define CHECK(cond)                                                               \
  do {                                                                            \
    check::checks()++;                                                            \
    if (!(cond)) {                                                                \
      check::failures()++;                                                        \
      std::printf("FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);                \
    }                                                                             \
  } while (0)

#define CHECK_EQ(a, b)                                                                        \
  do {                                                                                        \
    check::checks()++;                                                                        \
    long long va_ = static_cast<long long>(a), vb_ = static_cast<long long>(b);               \
    if (va_ != vb_) {                                                                         \
      check::failures()++;                                                                    \
      std::printf("FAIL %s:%d: %s == %s (%lld != %lld)\n", __FILE__, __LINE__, #a, #b, va_, vb_); \
    }                                                                                         \
  } while (0)

#define CHECK_NEAR(a, b, tol)                                                                \
  do {                                                                                       \
    check::checks()++;                                                                       \
    double va_ = (a), vb_ = (b);                                                             \
    if (!(std::fabs(va_ - vb_) <= (tol))) {                                                  \
      check::failures()++;                                                                   \
      std::printf("FAIL %s:%d: %s ~ %s (%.9g vs %.9g)\n", __FILE__, __LINE__, #a, #b, va_, vb_); \
    }                                                                                        \
  } while (0)

#endif
