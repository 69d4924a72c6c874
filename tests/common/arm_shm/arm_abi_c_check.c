/* arm_abi.h compiles as C11 (a driver on a microcontroller bridge is written in C) and its
   layout is the one the C++ side asserts: this program exits 0 when every offset agrees. */
#include <stddef.h>
#include <stdio.h>

#include "common/arm_shm/arm_abi.h"

int main(void) {
  int bad = 0;
  bad |= sizeof(somasim_arm_block_t) != 320;
  bad |= offsetof(somasim_arm_block_t, state) != 64;
  bad |= offsetof(somasim_arm_block_t, command) != 192;
  bad |= offsetof(somasim_arm_state_record_t, data) != 8;
  bad |= offsetof(somasim_arm_state_t, joint) != 24;
  bad |= offsetof(somasim_arm_state_t, gripper) != 88;
  bad |= offsetof(somasim_arm_command_t, torque) != 24;
  bad |= offsetof(somasim_arm_command_t, force) != 88;
  /* The seqlock's writer, as a C driver writes it. */
  somasim_arm_block_t block = {0};
  somasim_arm_state_record_t* rec = &block.state;
  uint64_t s = rec->sequence;
  __atomic_store_n(&rec->sequence, s + 1, __ATOMIC_RELAXED);
  __atomic_thread_fence(__ATOMIC_RELEASE);
  rec->data.heartbeat = 1;
  __atomic_store_n(&rec->sequence, s + 2, __ATOMIC_RELEASE);
  bad |= rec->sequence != 2;
  if (bad) printf("arm_abi.h: the C layout differs from the ABI\n");
  return bad;
}
