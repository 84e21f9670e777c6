// `streetsim serve` starts its training jobs' processes (`streetsim init`, `streetsim train`) with
// STREETSIM_PARENT_PID set to its own pid (server/job_runner.cc). Such a process must not outlive
// the server: a trainer left running after `kill -9` of its server would write beside the trainer
// that the restarted server starts for the same job.
#pragma once

namespace streetsim {

// When STREETSIM_PARENT_PID is set: the kernel sends this process SIGHUP when its parent dies
// (`streetsim train` answers with a checkpoint and exits; other commands end at once), and if the
// parent is already gone, the signal comes at once. SIGHUP rather than SIGTERM: the kernel sends
// it once per thread of the parent as they end, and a trainer's second SIGTERM means "kill now".
// Call first thing in main().
void DieWithParentServer();

// Whether this process was started by a server (STREETSIM_PARENT_PID set).
bool StartedByServer();

}  // namespace streetsim
