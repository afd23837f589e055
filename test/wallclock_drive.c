/*
 * wallclock_drive.c -- a drive library (im_drive.h) for the tests: the example drive's
 * stand-in plant, but living on the wall clock as a real power stage does. Each write and
 * each read first integrates the plant over every period Ts that went by since the last
 * call (CLOCK_MONOTONIC; the period boundaries half a period from where the loop calls --
 * the plant's clock starts at the first write and is set, at the ANCHOR_WRITES-th, to the
 * median phase of the writes so far: a first write that came late would otherwise put
 * every boundary near the on-time calls -- so the loop's on-time jitter never flips a
 * count) with the command in force then: a write acts from the instant it is made, and
 * a read samples the plant as it is at that instant. So the read right after a write does not show it yet -- the sample at the
 * next period start does: command delay 2, what this library declares (as any power
 * stage whose read returns the sample of the period start). A loop that starts late
 * finds the plant further on, the old command held, and nothing tells the plant.
 *
 * Every write is recorded where the test reads it after the process ended, in the file
 * named by IM_TEST_DRIVE_LOG (float64 slots, a memory map, the layout of
 * recording_hardware.py): [0] writes, [1] last isq_ref, [2] last load torque,
 * [3] im_drive_close calls, [4] writes after close, [5] largest |isq_ref| written,
 * [6] when the current was last set to zero from non-zero [s, CLOCK_MONOTONIC] (a stop's
 * first zero write).
 * IM_TEST_DRIVE_FAULT_AFTER=N: im_drive_read returns -3 (a drive fault) from its N-th call.
 * IM_TEST_DRIVE_DELAY=D: what im_drive_command_delay returns (default 2, the truth).
 */
#include <fcntl.h>
#include <math.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>

#include "im_drive.h"

#define TS 200.0e-6
#define KT 0.7100775862068965
#define J 0.0025
#define B 0.0003
#define ISD 2.45
#define BANDWIDTH 1500.0
#define TAU_W 0.001
#define COUNTS 4096.0
#define ANCHOR_WRITES 64
#define SLOTS 7

static double *slot;
static double a_i, a_w, cpr;
static double isq_ref, load_ref, isq, theta, omega, count, omega_meas, theta_meas;
static double t_plant = -1.0; /* [s] the plant integrated up to here */
static long reads, fault_after;
static double t_first;                /* [s] the first write */
static double phase[ANCHOR_WRITES];   /* [s] each early write's offset from the first's grid */
static int writes;
static int delay = 2, closed;

static double now_s(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

int im_drive_abi_version(void) { return IM_DRIVE_ABI_VERSION; }

int im_drive_open(const char *drive_file) {
  const char *path = getenv("IM_TEST_DRIVE_LOG");
  const char *f = getenv("IM_TEST_DRIVE_FAULT_AFTER");
  const char *d = getenv("IM_TEST_DRIVE_DELAY");
  (void)drive_file;
  if (path) {
    int fd = open(path, O_RDWR | O_CREAT | O_TRUNC, 0644);
    if (fd < 0 || ftruncate(fd, SLOTS * sizeof(double)) != 0) return -1;
    slot = mmap(NULL, SLOTS * sizeof(double), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (slot == MAP_FAILED) return -1;
  }
  fault_after = f ? atol(f) : 0;
  delay = d ? atoi(d) : 2;
  a_i = exp(-TS * BANDWIDTH);
  a_w = exp(-TS / TAU_W);
  cpr = COUNTS / (2.0 * M_PI);
  return 0;
}

int im_drive_command_delay(void) { return delay; }

static void period(void);

static void advance(int writing) { /* every period that went by, with the command in force */
  double now = now_s();
  if (t_plant < 0) {
    /* the plant's clock starts with the loop's first write (a period start), so that its
       boundaries lie half a period from where the loop calls; a read before it (a node
       that publishes its first state before its loop starts) samples the plant at rest */
    if (!writing) return;
    t_plant = now - TS;
  }
  while (t_plant + 0.5 * TS <= now) {
    period();
    t_plant += TS;
  }
}

static int by_value(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

/* the plant's period boundaries half a period from the loop's typical write: each of the
   first writes' offset from the first write's grid, wrapped into [-Ts/2, Ts/2), and the
   grid moved by their median once (a late write is rare, so the median is an on-time one) */
static void anchor(double now) {
  double r;
  if (writes == 0) t_first = now;
  if (writes < ANCHOR_WRITES) {
    r = fmod(now - t_first, TS);
    phase[writes] = r >= 0.5 * TS ? r - TS : r;
  }
  writes += 1;
  if (writes == ANCHOR_WRITES) {
    qsort(phase, ANCHOR_WRITES, sizeof phase[0], by_value);
    t_plant += phase[ANCHOR_WRITES / 2];
  }
}

int im_drive_write(double i, double load) {
  double now = now_s();
  advance(1);
  anchor(now);
  if (slot) {
    slot[0] += 1.0;
    slot[1] = i;
    slot[2] = load;
    if (closed) slot[4] += 1.0;
    if (fabs(i) > slot[5]) slot[5] = fabs(i);
    if (i == 0.0 && isq_ref != 0.0) slot[6] = now;
  }
  isq_ref = i;
  load_ref = load;
  return 0;
}

static void period(void) {
  double c, raw;
  isq = a_i * isq + (1.0 - a_i) * isq_ref;
  omega += (KT * isq - load_ref - B * omega) / J * TS;
  theta += omega * TS;
  c = floor(theta * cpr);
  raw = (c - count) / (cpr * TS);
  count = c;
  theta_meas = c / cpr;
  omega_meas = a_w * omega_meas + (1.0 - a_w) * raw;
}

int im_drive_read(double m[8]) {
  reads += 1;
  if (fault_after > 0 && reads >= fault_after) return -3;
  advance(0);
  m[IM_DRIVE_THETA_MEAS] = theta_meas;
  m[IM_DRIVE_OMEGA_MEAS] = omega_meas;
  m[IM_DRIVE_TORQUE] = KT * isq;
  m[IM_DRIVE_ISD] = ISD;
  m[IM_DRIVE_ISQ] = isq;
  m[IM_DRIVE_I_ALPHA] = cos(theta_meas) * ISD - sin(theta_meas) * isq;
  m[IM_DRIVE_I_BETA] = sin(theta_meas) * ISD + cos(theta_meas) * isq;
  m[IM_DRIVE_LOAD_TORQUE] = load_ref;
  return 0;
}

void im_drive_close(void) {
  closed = 1;
  if (slot) slot[3] += 1.0;
}
