// Runs every registered test; exit status 0 only if all checks passed. The last line is the
// summary pytest reads: "unit_tests: T tests, C checks, F failed".
#include "check.h"

namespace check {
Test *&registry() { static Test *head = nullptr; return head; }
int &checks() { static int n = 0; return n; }
int &failures() { static int n = 0; return n; }
}  // namespace check

int main() {
  int tests = 0;
  for (check::Test *t = check::registry(); t; t = t->next) {
    int before = check::failures();
    t->fn();
    tests++;
    std::printf("%s %s\n", check::failures() == before ? "ok  " : "FAIL", t->name);
  }
  std::printf("unit_tests: %d tests, %d checks, %d failed\n", tests, check::checks(), check::failures());
  return check::failures() ? 1 : 0;
}
