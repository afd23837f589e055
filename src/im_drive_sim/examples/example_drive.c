/*
 * example_drive.c -- the example drive's stand-in plant as a drive library (im_drive.h):
 * the same plant as im_drive_sim.example_drive.Hardware and example_hardware's compiled
 * form (a first-order current loop, torque = kt isq, inertia and viscous friction, a
 * 4096-count encoder, a low-pass filtered backward-difference speed), the same numbers.
 *
 * A template for a vendor SDK: replace the bodies of im_drive_write and im_drive_read with
 * your inverter's interface. The stand-in takes its constants at build time (the packaged
 * 750 W motor by default; -DIM_KT=... for another), as a vendor library reads its own
 * configuration, and advances its plant by one period in each read: a simulated plant,
 * paced by the loop. Build:
 *
 *   cc -O2 -shared -fPIC -I$(ros2 pkg prefix im_drive_sim)/share/im_drive_sim/include \
 *      -o libexample_drive.so example_drive.c -lm
 *   ros2 run im_tuner tuner --bench realtime --drive lib:./libexample_drive.so
 */
#include <math.h>
#include <stddef.h>

#include "im_drive.h"

#ifndef IM_TS
#define IM_TS 200.0e-6 /* [s] */
#endif
#ifndef IM_KT
#define IM_KT 0.7100775862068965 /* [N m/A] */
#endif
#ifndef IM_J
#define IM_J 0.0025 /* [kg m^2] */
#endif
#ifndef IM_B
#define IM_B 0.0003 /* [N m s/rad] */
#endif
#ifndef IM_ISD
#define IM_ISD 2.45 /* [A] */
#endif
#ifndef IM_POLE_PAIRS
#define IM_POLE_PAIRS 1.0
#endif
#ifndef IM_CURRENT_BANDWIDTH
#define IM_CURRENT_BANDWIDTH 1500.0 /* [rad/s] */
#endif
#ifndef IM_SPEED_FILTER_TAU
#define IM_SPEED_FILTER_TAU 0.001 /* [s] */
#endif
#ifndef IM_ENCODER_COUNTS
#define IM_ENCODER_COUNTS 4096.0
#endif
#ifndef IM_COMMAND_DELAY
#define IM_COMMAND_DELAY 1
#endif

static double a_i, a_w, cpr, inv_j;
static double isq_ref, load_ref, next_isq, next_load; /* the command acting; delay 2's next */
static double isq, theta, omega, count;               /* the true plant */
static double theta_meas, omega_meas;                 /* the encoder's position and speed */

int im_drive_abi_version(void) { return IM_DRIVE_ABI_VERSION; }

int im_drive_open(const char *drive_file) {
  (void)drive_file; /* the stand-in's constants are compiled in */
  a_i = exp(-IM_TS * IM_CURRENT_BANDWIDTH);
  a_w = IM_SPEED_FILTER_TAU > 0 ? exp(-IM_TS / IM_SPEED_FILTER_TAU) : 0.0;
  cpr = IM_ENCODER_COUNTS / (2.0 * M_PI);
  inv_j = 1.0 / IM_J;
  isq_ref = load_ref = next_isq = next_load = 0.0;
  isq = theta = omega = count = theta_meas = omega_meas = 0.0;
  return 0;
}

int im_drive_command_delay(void) { return IM_COMMAND_DELAY; }

int im_drive_write(double isq_ref_, double load_torque) {
  if (IM_COMMAND_DELAY == 2) {
    next_isq = isq_ref_;
    next_load = load_torque;
  } else {
    isq_ref = isq_ref_;
    load_ref = load_torque;
  }
  return 0;
}

int im_drive_read(double m[8]) {
  double load = load_ref, torque, c, raw, rho;
  isq = a_i * isq + (1.0 - a_i) * isq_ref; /* one period of the plant */
  torque = IM_KT * isq;
  omega += (torque - load_ref - IM_B * omega) * inv_j * IM_TS;
  theta += omega * IM_TS;
  if (IM_COMMAND_DELAY == 2) {
    isq_ref = next_isq;
    load_ref = next_load;
  }
  c = floor(theta * cpr); /* the encoder */
  raw = (c - count) / (cpr * IM_TS);
  count = c;
  theta_meas = c / cpr;
  omega_meas = a_w * omega_meas + (1.0 - a_w) * raw;
  rho = IM_POLE_PAIRS * theta_meas;
  m[IM_DRIVE_THETA_MEAS] = theta_meas;
  m[IM_DRIVE_OMEGA_MEAS] = omega_meas;
  m[IM_DRIVE_TORQUE] = torque;
  m[IM_DRIVE_ISD] = IM_ISD;
  m[IM_DRIVE_ISQ] = isq;
  m[IM_DRIVE_I_ALPHA] = cos(rho) * IM_ISD - sin(rho) * isq;
  m[IM_DRIVE_I_BETA] = sin(rho) * IM_ISD + cos(rho) * isq;
  m[IM_DRIVE_LOAD_TORQUE] = load;
  return 0;
}

void im_drive_close(void) {}
