// Child processes: input, output, exit status, signals, time limits and spawn failures.
#include <catch2/catch.hpp>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "turnfit/io/process.hpp"

using namespace turnfit;

TEST_CASE("run_process: stdin in, stdout and stderr apart, exit status", "[process]") {
  ProcessSpec s;
  s.argv = shell_argv("cat; echo oops >&2; exit 3");
  s.input = "hello\n";
  const ProcessResult r = run_process(s);
  CHECK(r.started);
  CHECK(r.out == "hello\n");
  CHECK(r.err == "oops\n");
  CHECK(r.exit_code == 3);
  CHECK_FALSE(r.ok());
  CHECK(r.describe(0) == "exit 3");
  s.argv = {"pwd"};
  s.cwd = "/usr";
  CHECK(run_process(s).out == "/usr\n");
  s.cwd = "/nonexistent-folder";
  CHECK_FALSE(run_process(s).started);
}

TEST_CASE("run_process: megabytes both ways without a deadlock, a child that never reads", "[process]") {
  ProcessSpec s;
  s.argv = {"cat"};
  s.input.assign(3u << 20, 'x');
  ProcessResult r = run_process(s);
  CHECK(r.ok());
  CHECK(r.out.size() == s.input.size());
  // The child exits without reading: no SIGPIPE kills the caller, the status is the child's.
  s.argv = {"true"};
  r = run_process(s);
  CHECK(r.ok());
  s.max_output = 1000;
  s.argv = {"cat"};
  r = run_process(s);
  CHECK(r.out.size() == 1000);
}

TEST_CASE("run_process: time limit kills the whole process group, signals reported", "[process]") {
  ProcessSpec s;
  s.argv = shell_argv("sleep 30 & sleep 30; echo never");
  s.timeout_s = 0.3;
  const auto t0 = std::chrono::steady_clock::now();
  ProcessResult r = run_process(s);
  const double took = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  CHECK(r.timed_out);
  CHECK(took < 5);  // the background sleep held stdout open: it was killed with its group
  CHECK(r.out.empty());
  CHECK(r.describe(0.3).find("timed out") == 0);
  s.argv = shell_argv("kill -SEGV $$");
  s.timeout_s = 10;
  r = run_process(s);
  CHECK(r.signal == 11);
  CHECK_FALSE(r.ok());
}

TEST_CASE("run_process: a missing program is reported, not thrown, threads do not share pipes", "[process]") {
  ProcessSpec s;
  s.argv = {"/nonexistent/program"};
  ProcessResult r = run_process(s);
  CHECK_FALSE(r.started);
  CHECK(r.spawn_error.find("No such file") != std::string::npos);
  s.argv = {"no-such-program-turnfit"};
  CHECK_FALSE(run_process(s).started);
  // A slow child in one thread must not hold another thread's quick child's pipes open.
  std::thread slow([] {
    ProcessSpec t;
    t.argv = shell_argv("sleep 2");
    run_process(t);
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  std::vector<double> took;
  for (int i = 0; i < 5; ++i) {
    ProcessSpec q;
    q.argv = shell_argv("echo $0");
    const auto t0 = std::chrono::steady_clock::now();
    const ProcessResult qr = run_process(q);
    took.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    CHECK(qr.ok());
  }
  slow.join();
  for (double t : took) CHECK(t < 1.5);
}
