/* The shared-memory ABI between somasim-haptic (the "node") and a haptic arm's driver (SPEC §1,
 * issue 9; docs/arm_abi.md tells driver authors how to implement their side).
 *
 * C11 and C++: fixed layout, no pointers, little-endian 64-bit hosts (x86-64, AArch64). One
 * POSIX shared-memory object per arm, named "/somasim-arm-<NAME>" (NAME: 1-32 letters, digits,
 * '_' or '-'), holding one somasim_arm_block_t:
 *
 *   offset   0  header (64 bytes): magic, ABI version, the sizes below, the arm's joint count
 *   offset  64  arm -> node record (128 bytes): sequence + somasim_arm_state_t, written by the
 *               driver only
 *   offset 192  node -> arm record (128 bytes): sequence + somasim_arm_command_t, written by the
 *               node only
 *
 * Each record is a single-writer seqlock. The writer increments `sequence` (making it odd),
 * writes the payload, then increments `sequence` again (even) with release ordering; a reader
 * loads `sequence` (acquire), copies the payload, loads `sequence` again after an acquire fence,
 * and keeps the copy only if both loads are equal and even. In C with GCC or Clang:
 *
 *   writer:  uint64_t s = rec->sequence;
 *            __atomic_store_n(&rec->sequence, s + 1, __ATOMIC_RELAXED);
 *            __atomic_thread_fence(__ATOMIC_RELEASE);
 *            ... store the payload (8-byte words, relaxed atomic stores) ...
 *            __atomic_store_n(&rec->sequence, s + 2, __ATOMIC_RELEASE);
 *   reader:  s1 = __atomic_load_n(&rec->sequence, __ATOMIC_ACQUIRE);  (odd: retry)
 *            ... load the payload (relaxed atomic loads) ...
 *            __atomic_thread_fence(__ATOMIC_ACQUIRE);
 *            s2 = __atomic_load_n(&rec->sequence, __ATOMIC_RELAXED);  (s1 != s2: retry)
 *
 * Whoever creates the object fills the header and stores `magic` last (release); the other side
 * waits for the magic and refuses a block whose magic, version or sizes differ from its own.
 * Heartbeats count each side's cycles: the driver zeroes its torques by itself when the node's
 * heartbeat has not changed for 10 ms (its watchdog), and the node stops commanding when the
 * driver's has not changed for 10 ms. Time stamps are each side's own monotonic clock, for logs
 * only (clocks are never compared across sides). */
#ifndef SOMASIM_COMMON_ARM_SHM_ARM_ABI_H_
#define SOMASIM_COMMON_ARM_SHM_ARM_ABI_H_

#include <stddef.h>
#include <stdint.h>

#define SOMASIM_ARM_MAGIC UINT32_C(0x4D524153) /* the bytes "SARM" */
#define SOMASIM_ARM_ABI_VERSION UINT32_C(1)
#define SOMASIM_ARM_MAX_JOINTS 8
#define SOMASIM_ARM_SHM_PREFIX "/somasim-arm-"

/* somasim_arm_state_t.buttons */
#define SOMASIM_ARM_BUTTON_CLUTCH UINT32_C(1)         /* held: the tool stays put */
#define SOMASIM_ARM_BUTTON_EMERGENCY_STOP UINT32_C(2) /* pressed: no force, at once */
#define SOMASIM_ARM_BUTTON_CUT UINT32_C(4)            /* scalpel engaged */

/* Arm -> node: what the driver reads from the arm. 96 bytes. */
typedef struct somasim_arm_state {
  uint64_t driver_time_ns;              /* the driver's monotonic clock [ns], for logs only */
  uint64_t heartbeat;                   /* +1 per driver cycle (1 kHz or faster) */
  uint32_t buttons;                     /* SOMASIM_ARM_BUTTON_* */
  uint32_t num_joints;                  /* valid entries of joint[]: the header's num_joints */
  double joint[SOMASIM_ARM_MAX_JOINTS]; /* [rad] revolute or [m] prismatic, after the driver's
                                           encoder scaling; homing offsets are the node's */
  double gripper;                       /* 0 open .. 1 closed */
} somasim_arm_state_t;

/* Node -> arm: what the driver applies. 120 bytes. */
typedef struct somasim_arm_command {
  uint64_t node_time_ns;                 /* the node's monotonic clock [ns], for logs only */
  uint64_t heartbeat;                    /* +1 per node tick (1 kHz) */
  uint32_t enable;                       /* 0: the motors must produce no torque */
  uint32_t num_joints;                   /* valid entries of torque[] */
  double torque[SOMASIM_ARM_MAX_JOINTS]; /* [N m] revolute or [N] prismatic: J^T force */
  double force[3]; /* [N] the Cartesian force in the arm's base frame they render (for logs) */
  double reserved; /* 0 */
} somasim_arm_command_t;

typedef struct somasim_arm_state_record {
  uint64_t sequence; /* seqlock: odd while the driver writes */
  somasim_arm_state_t data;
  uint8_t padding[128 - 8 - sizeof(somasim_arm_state_t)];
} somasim_arm_state_record_t;

typedef struct somasim_arm_command_record {
  uint64_t sequence; /* seqlock: odd while the node writes */
  somasim_arm_command_t data;
} somasim_arm_command_record_t;

typedef struct somasim_arm_block {
  uint32_t magic;                       /* SOMASIM_ARM_MAGIC, stored last by the creator */
  uint32_t abi_version;                 /* SOMASIM_ARM_ABI_VERSION */
  uint32_t block_size;                  /* sizeof(somasim_arm_block_t) = 320 */
  uint32_t state_size;                  /* sizeof(somasim_arm_state_t) = 96 */
  uint32_t command_size;                /* sizeof(somasim_arm_command_t) = 120 */
  uint32_t num_joints;                  /* the arm's joints, 1 .. SOMASIM_ARM_MAX_JOINTS */
  uint8_t reserved[40];                 /* 0 */
  somasim_arm_state_record_t state;     /* offset 64 */
  somasim_arm_command_record_t command; /* offset 192 */
} somasim_arm_block_t;

#ifdef __cplusplus
static_assert(sizeof(somasim_arm_state_t) == 96, "ABI");
static_assert(sizeof(somasim_arm_command_t) == 120, "ABI");
static_assert(sizeof(somasim_arm_block_t) == 320, "ABI");
static_assert(offsetof(somasim_arm_block_t, state) == 64, "ABI");
static_assert(offsetof(somasim_arm_block_t, command) == 192, "ABI");
#else
_Static_assert(sizeof(somasim_arm_state_t) == 96, "ABI");
_Static_assert(sizeof(somasim_arm_command_t) == 120, "ABI");
_Static_assert(sizeof(somasim_arm_block_t) == 320, "ABI");
#endif

#endif /* SOMASIM_COMMON_ARM_SHM_ARM_ABI_H_ */
