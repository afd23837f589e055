/*
 * im_drive.h -- the drive ABI of im_tuner's real-time loop (docs/real-drive.md,
 * "A drive library").
 *
 * A power stage given as a C shared library runs inside the compiled 5 kHz loop of
 * `ros2 run im_tuner tuner --bench realtime --drive lib:PATH` (and of
 * `ros2 run im_drive_sim example_drive --hardware lib:PATH`), called by address, with no
 * Python in the period. Modelled on ros2_control's hardware_interface::SystemInterface:
 * im_drive_open ~ on_configure/on_activate, im_drive_write ~ write, im_drive_read ~ read,
 * im_drive_close ~ on_deactivate.
 *
 * Once per period Ts, at its start, the loop calls im_drive_write with the newest
 * command (already clamped to +-isq_max; zero before the first command and after a stop),
 * then im_drive_read. Both must return within the period: do blocking I/O elsewhere (the
 * inverter's own cyclic exchange, a thread of the library) and touch a buffer here. They
 * run in the loop's thread (SCHED_FIFO when asked): never sleep, lock or allocate.
 *
 * Return codes: 0 = done; a negative value is a drive fault: the loop writes zero current
 * (im_drive_write(0, 0)), stops, and the run ends in one line naming the library, the
 * function and the code.
 *
 * Every way out of a run (its end, SIGINT, SIGTERM, a fault, an exception) ends with a last
 * im_drive_write(0.0, 0.0), then im_drive_close() once. SIGKILL and a power cut cannot:
 * the inverter needs its own communication-loss trip.
 */
#ifndef IM_DRIVE_H
#define IM_DRIVE_H

#ifdef __cplusplus
extern "C" {
#endif

/* The version of this interface. It changes whenever a function's signature or meaning,
 * or the layout of m[], changes; a library built against another version is refused
 * before im_drive_open is called (one line, exit 2). Version 1: the functions below. */
#define IM_DRIVE_ABI_VERSION 1

/* Required. Return IM_DRIVE_ABI_VERSION, the version of this header the library was
 * built against: { return IM_DRIVE_ABI_VERSION; }. Called first, once. */
int im_drive_abi_version(void);

/* The fields of im_drive_read's m[], in order (SI units; d/q in the rotor-flux frame). */
enum im_drive_measurement {
  IM_DRIVE_THETA_MEAS = 0, /* [rad]   encoder position, multi-turn, unwrapped */
  IM_DRIVE_OMEGA_MEAS = 1, /* [rad/s] speed estimate */
  IM_DRIVE_TORQUE = 2,     /* [N m]   electromagnetic torque (estimate) */
  IM_DRIVE_ISD = 3,        /* [A]     d-axis (flux) current */
  IM_DRIVE_ISQ = 4,        /* [A]     q-axis (torque) current */
  IM_DRIVE_I_ALPHA = 5,    /* [A]     stator current, stationary frame */
  IM_DRIVE_I_BETA = 6,     /* [A] */
  IM_DRIVE_LOAD_TORQUE = 7, /* [N m]  the load machine's torque (0 without one) */
  IM_DRIVE_N_MEASUREMENT = 8
};

/* Required. Called once before the first period. drive_file: the absolute path of the
 * --drive-config file, or NULL (the packaged motor). Returns 0 when the power stage is
 * ready; anything else refuses the run (one line, exit 2, nothing created). */
int im_drive_open(const char *drive_file);

/* Required. The q-current reference isq_ref [A] and the load machine's torque
 * load_torque [N m] for the coming period. 0, or a negative fault code. */
int im_drive_write(double isq_ref, double load_torque);

/* Required. Sample the sensors now into m[IM_DRIVE_N_MEASUREMENT]. 0, or a negative fault
 * code. */
int im_drive_read(double m[8]);

/* Optional. Over which period a write acts: 1 (the period that starts with it, the
 * default) or 2 (a power stage that latches its reference at the period start). */
int im_drive_command_delay(void);

/* Optional. Called once, after the last im_drive_write(0.0, 0.0): disable the power
 * stage, release the bus. */
void im_drive_close(void);

#ifdef __cplusplus
}
#endif

#endif /* IM_DRIVE_H */
