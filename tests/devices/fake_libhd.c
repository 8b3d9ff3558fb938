/* A fake OpenHaptics HD library for the tests: the exported functions and signatures the
 * touchx backend uses (hdDefines.h / hdScheduler.h / hdDevice.h of OpenHaptics 3.x), a scheduler
 * thread at the requested rate, and fake_* hooks for the tests.
 *
 * It refuses and degrades as the real library and a real Touch X do (OpenHaptics Programmer's
 * Guide and API reference, the Calibration and PreventWarmMotors examples):
 * - calibration: a device reports NEEDS_MANUAL_INPUT until its stylus is in the inkwell, then
 *   NEEDS_UPDATE until hdUpdateCalibration(HD_CALIBRATION_INKWELL) (AUTO: NEEDS_UPDATE until
 *   hdUpdateCalibration(HD_CALIBRATION_AUTO)); the update takes cal_delay ticks, and while it
 *   is not calibrated the position is off by cal_offset mm, so it jumps when calibration ends.
 *   HD_CALIBRATION_ENCODER_RESET zeroes the encoders wherever the arm is: unless the arm is at
 *   its reset pose every position after it is off by the distance to that pose.
 * - forces: the device's HD_NOMINAL_MAX_FORCE (peak) and HD_NOMINAL_MAX_CONTINUOUS_FORCE;
 *   a force over the peak gives HD_EXCEEDED_MAX_FORCE (clamped with HD_MAX_FORCE_CLAMPING, else
 *   cut). The motors' temperature (HD_MOTOR_TEMPERATURE, 0 room .. 1 overheat) follows the
 *   squared force with time constant tau_s (10 s: a guess, 3D Systems publishes none): the
 *   continuous force holds it at 0.6; at 1 the device raises HD_WARM_MOTORS (and again every
 *   second while warm, until it is below 0.7).
 * - scheduler watchdog: a tick whose callbacks run longer than watchdog_us gives
 *   HD_TIMER_ERROR ("unable to maintain the servo loop timer") and the force is cut for that
 *   tick; hdGetSchedulerTimeStamp() is the time since the tick began. It is off until a test
 *   sets it (fake_set_watchdog_us, or FAKE_HD_WATCHDOG_US for a servo in another process):
 *   an HD_TIMER_ERROR now stops the callback and re-initialises the device, and a busy test
 *   machine's stall is no defect of the code under test (the bench counts the would-be trips
 *   from the duration histogram instead).
 * - the scheduler thread: OpenHaptics' libHD starts its servo loop through the Touch driver
 *   (startServoLoop in libPHANToMIO / libPhantomIOLib42, closed source: libHD 3.0 calls no
 *   pthread or sched function itself), so whether it inherits its creator's SCHED_FIFO is not
 *   known. The fake takes the case that needs the caller to act: its thread is created with
 *   PTHREAD_EXPLICIT_SCHED and SCHED_OTHER, at normal priority whatever the policy of the
 *   thread that called hdStartScheduler; only the callback, from inside the thread, can raise
 *   it. fake_thread_policy() reads the thread's policy back.
 * - unplugging (fake_unplug): the servo loop loses the device: every tick raises HD_COMM_ERROR
 *   and the motors are off; hdInitDevice fails with HD_COMM_ERROR while it is unplugged. A
 *   replugged device (fake_replug) comes back only through a new hdInitDevice: the session that
 *   saw it go keeps raising HD_COMM_ERROR (a stale handle) until the device is disabled and
 *   initialised again. A test in another process unplugs it by creating the file named by
 *   the environment variable FAKE_HD_UNPLUG_FILE (checked every 10 ticks and by hdInitDevice)
 *   and replugs it by removing the file; FAKE_HD_WATCHDOG_US sets the watchdog (0: off).
 * - the 3D Systems Touch driver (libPhantomIOLib42) needs GTDD_HOME: without it hdInitDevice
 *   prints the driver's "Config directory not set correctly." and fails (HD_COMM_ERROR: a
 *   guess; users report only that the Touch is then not found, jhu-cisst-external/
 *   3ds-touch-openhaptics issue 2, and the backend's message does not depend on the code).
 * It also keeps the callbacks' period and duration (tick start to the callbacks' return, so a
 * Python callback's wait for its GIL is counted) in 10 us histograms. */
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

typedef struct { unsigned int errorCode; int internalErrorCode; unsigned int hHD; } HDErrorInfo;
typedef unsigned int (*HDSchedulerCallback)(void *);

#define OK 0x5000
#define NEEDS_UPDATE 0x5001
#define NEEDS_MANUAL 0x5002
#define ENC_RESET (1 << 0)
#define AUTO (1 << 1)
#define INKWELL (1 << 2)
#define NBINS 5000 /* 10 us bins: 0 .. 50 ms */

#define MAXCB 8
static HDSchedulerCallback cbs[MAXCB];
static void *cb_data[MAXCB];
static unsigned short cb_prio[MAXCB];
static int ncb;
static volatile int running, manual, inited, enabled, in_frame, clamping, ramping;
static pthread_t thread, servo_thread;
static int have_servo_thread;
static volatile long servo_tid;  /* the scheduler thread's kernel id (0: not yet) */
static unsigned long rate = 1000;  /* OpenHaptics' default too */
static volatile long ticks, frames, force_writes, frame_violations, thread_violations;
static double T[16] = {1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1};  /* true pose, column-major, mm */
static double V[3];
static int buttons;
static double force[3], max_force_seen, nominal_max_force = 7.9, nominal_continuous = 1.75;
static double temperature, tau_s = 10.0;
static int warm;
static long warm_events, exceeded_events, watchdog_trips, last_warm_tick;
static unsigned int calibration = OK, last_update_style;
static int calibration_style = AUTO, inkwell, at_reset_pose;
static long cal_delay = 50, cal_pending = -1;
static unsigned int cal_pending_style;
static double cal_offset[3] = {12.0, -8.0, 5.0}, offset[3];
static double reset_pose[3] = {0.0, -65.0, -90.0};  /* mm, where the links are orthogonal */
static long enc_reset_running, updates;
static unsigned int err_queue[16]; static int err_internal[16]; static volatile int nerr;
static unsigned int init_error;
static int unplugged, session_lost;  /* the device is gone; this handle saw it go */
static long inits;
static int require_gtdd = 1;
static long fail_at_tick = -1; static unsigned int fail_code;
static long watchdog_ns;  /* off until a test sets it: see the top of the file */
static struct timespec tick_start, last_tick_start;
static long period_hist[NBINS], dur_hist[NBINS], nperiods, ndurs;
static double dur_max_us, period_max_us;

static void push_error(unsigned int code, int internal) {
    if (nerr < 16) { err_queue[nerr] = code; err_internal[nerr] = internal; nerr++; }
}
static int in_servo(void) {
    return !have_servo_thread || pthread_equal(pthread_self(), servo_thread);
}
static double ns_between(const struct timespec *a, const struct timespec *b) {
    return (double)(b->tv_sec - a->tv_sec) * 1e9 + (double)(b->tv_nsec - a->tv_nsec);
}
static void hist_add(long *h, double us) {
    long i = (long)(us / 10.0);
    h[i < 0 ? 0 : i >= NBINS ? NBINS - 1 : i]++;
}
static void set_uncalibrated_offset(void) { memcpy(offset, cal_offset, sizeof offset); }

static int unplug_file_says = -1;  /* what the unplug file said last (-1: no file named) */
static void check_unplug_file(void) {
    const char *f = getenv("FAKE_HD_UNPLUG_FILE");
    if (!f) return;
    int out = access(f, F_OK) == 0;
    if (out != unplug_file_says) {
        unplug_file_says = out;
        if (out) { unplugged = 1; if (inited) session_lost = 1; } else unplugged = 0;
    }
}

unsigned int hdInitDevice(const char *name) {
    const char *w = getenv("FAKE_HD_WATCHDOG_US");  /* a test in another process sets it */
    if (w) watchdog_ns = atol(w) * 1000L;
    check_unplug_file();
    if (require_gtdd && !getenv("GTDD_HOME")) {
        fprintf(stderr, "Config directory not set correctly.: No such file or directory\n");
        push_error(0x0302, -1);
        return 0xFFFFFFFF;
    }
    if (init_error) { push_error(init_error, -3); return 0xFFFFFFFF; }
    if (unplugged) { push_error(0x0302, -4); return 0xFFFFFFFF; }
    if (inited) { push_error(0x0301, 0); return 0xFFFFFFFF; }  /* HD_DEVICE_ALREADY_INITIATED */
    inited = 1; session_lost = 0; inits++; return 1;
}
void hdDisableDevice(unsigned int h) { inited = 0; enabled = 0; }
void hdMakeCurrentDevice(unsigned int h) {}
HDErrorInfo hdGetError(void) {
    HDErrorInfo e = {0, 0, 1};
    if (nerr > 0) {  /* errors come off a stack, most recent first (as in HD) */
        nerr--; e.errorCode = err_queue[nerr]; e.internalErrorCode = err_internal[nerr];
    }
    return e;
}
void hdEnable(unsigned int cap) {
    if (cap == 0x4000) enabled = 1;
    else if (cap == 0x4001) clamping = 1;
    else if (cap == 0x4002) ramping = 1;
    else push_error(0x0100, 0);
}
void hdBeginFrame(unsigned int h) {
    if (in_frame) push_error(0x0400, 0);
    if (!in_servo()) thread_violations++;
    in_frame = 1;
}
void hdEndFrame(unsigned int h) {
    if (!in_frame) push_error(0x0401, 0);
    in_frame = 0; frames++;
}
void hdGetDoublev(unsigned int what, double *v) {
    if (what == 0x2052) {  /* HD_CURRENT_TRANSFORM: the encoders' idea of the pose */
        memcpy(v, T, sizeof T);
        for (int i = 0; i < 3; i++) v[12 + i] += offset[i];
    } else if (what == 0x2051) memcpy(v, V, sizeof V);
    else if (what == 0x2603) *v = nominal_max_force;
    else if (what == 0x2604) *v = nominal_continuous;
    else if (what == 0x2605) { v[0] = v[1] = v[2] = temperature; }  /* 3 motors */
    else if (what == 0x2700) memcpy(v, force, sizeof force);
    else push_error(0x0100, 0);
}
void hdGetIntegerv(unsigned int what, int *v) {
    if (what == 0x2000) *v = buttons;
    else if (what == 0x2555) *v = calibration_style;
    else push_error(0x0100, 0);
}
const char *hdGetString(unsigned int what) {
    if (what == 0x2501) return "Touch X (fake)";
    if (what == 0x2504) return "00000-fake";
    return 0;
}
void hdSetDoublev(unsigned int what, const double *v) {
    if (what != 0x2700) { push_error(0x0100, 0); return; }
    if (!in_frame || !in_servo()) { frame_violations++; push_error(0x0402, 0); return; }
    double m = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    double s = 1.0;
    if (!(m <= nominal_max_force)) {  /* over the peak (or NaN): the amplifiers refuse it */
        exceeded_events++;
        push_error(0x0201, 0);
        s = (clamping && isfinite(m)) ? nominal_max_force / m : 0.0;
    }
    if (session_lost) s = 0.0;  /* nothing reaches a device that is gone */
    for (int i = 0; i < 3; i++) force[i] = v[i] * s;
    m *= s;
    if (m * m > max_force_seen) max_force_seen = m * m;
    force_writes++;
}
unsigned int hdCheckCalibration(void) { return calibration; }
void hdUpdateCalibration(unsigned int style) {
    last_update_style = style; updates++;
    if (!(style & calibration_style) || (style & (style - 1))) { push_error(0x0101, 0); return; }
    if (style == ENC_RESET) {  /* the encoders read the reset pose wherever the arm is */
        if (running) enc_reset_running++;
        for (int i = 0; i < 3; i++) offset[i] = at_reset_pose ? 0.0 : reset_pose[i] - T[12 + i];
        calibration = OK; cal_pending = -1;
        return;
    }
    if (calibration != NEEDS_UPDATE) return;  /* manual input first (the inkwell) */
    if (style == INKWELL && !inkwell) return;
    if (cal_pending < 0) { cal_pending = cal_delay; cal_pending_style = style; }
}
void hdSetSchedulerRate(unsigned long r) {
    if (r < 100 || r > 2000) { push_error(0x0101, 0); return; }
    rate = r;
}
unsigned long hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, unsigned short prio) {
    for (int i = 0; i < ncb; i++)  /* a slot freed by hdUnschedule or HD_CALLBACK_DONE */
        if (!cbs[i]) { cbs[i] = cb; cb_data[i] = data; cb_prio[i] = prio; return i + 1; }
    if (ncb >= MAXCB) { push_error(0x0501, 0); return 0; }
    cbs[ncb] = cb; cb_data[ncb] = data; cb_prio[ncb] = prio; return (unsigned long)(++ncb);
}
void hdUnschedule(unsigned long h) { if (h >= 1 && h <= (unsigned long)ncb) cbs[h - 1] = 0; }
double hdGetSchedulerTimeStamp(void) {
    struct timespec now; clock_gettime(CLOCK_MONOTONIC, &now);
    return ns_between(&tick_start, &now) * 1e-9;
}

static void calibration_step(void) {
    if (calibration == NEEDS_MANUAL && inkwell && (calibration_style & INKWELL))
        calibration = NEEDS_UPDATE;
    if (cal_pending > 0) cal_pending--;
    if (cal_pending == 0) {  /* done: the pose jumps to the true one */
        if (cal_pending_style != INKWELL || inkwell) {
            calibration = OK; memset(offset, 0, sizeof offset);
        }
        cal_pending = -1;
    }
}
static void thermal_step(void) {
    double f2 = force[0] * force[0] + force[1] * force[1] + force[2] * force[2];
    double target = 0.6 * f2 / (nominal_continuous * nominal_continuous);
    temperature += (target - temperature) / ((double)rate * tau_s);
    if (!warm && temperature >= 1.0) {
        warm = 1; warm_events++; last_warm_tick = ticks; push_error(0x0200, 0);
    } else if (warm && temperature < 0.7) {
        warm = 0;
    } else if (warm && ticks - last_warm_tick >= (long)rate) {
        last_warm_tick = ticks; push_error(0x0200, 0);
    }
}
static void one_tick(void) {
    struct timespec end;
    clock_gettime(CLOCK_MONOTONIC, &tick_start);
    if (ticks > 0) {
        double p = ns_between(&last_tick_start, &tick_start) / 1e3;
        hist_add(period_hist, p); nperiods++;
        if (p > period_max_us) period_max_us = p;
    }
    last_tick_start = tick_start;
    if (fail_at_tick >= 0 && ticks == fail_at_tick) push_error(fail_code, 7);
    if (ticks % 10 == 0) check_unplug_file();
    if (session_lost) { push_error(0x0302, -5); memset(force, 0, sizeof force); }
    calibration_step();
    for (int i = 0; i < ncb; i++)
        if (cbs[i] && cbs[i](cb_data[i]) == 0) cbs[i] = 0;  /* HD_CALLBACK_DONE */
    clock_gettime(CLOCK_MONOTONIC, &end);
    double d = ns_between(&tick_start, &end);
    hist_add(dur_hist, d / 1e3); ndurs++;
    if (d / 1e3 > dur_max_us) dur_max_us = d / 1e3;
    if (watchdog_ns > 0 && d > (double)watchdog_ns) {  /* the servo loop missed its slot */
        watchdog_trips++;
        push_error(0x0304, (int)(d / 1e3));
        memset(force, 0, sizeof force);
    }
    thermal_step();
    ticks++;
}
static void *servo_main(void *arg) {
    servo_tid = (long)syscall(SYS_gettid);
    struct timespec next; clock_gettime(CLOCK_MONOTONIC, &next);
    long period_ns = 1000000000L / (long)rate;
    while (running) {
        next.tv_nsec += period_ns;
        while (next.tv_nsec >= 1000000000L) { next.tv_nsec -= 1000000000L; next.tv_sec++; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, 0);
        if (running) one_tick();
    }
    return 0;
}
void hdStartScheduler(void) {
    if (running) return;
    running = 1;
    if (!manual) {
        pthread_attr_t attr;  /* normal priority, not inherited: see the top of the file */
        struct sched_param sp = {.sched_priority = 0};
        pthread_attr_init(&attr);
        pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
        pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
        pthread_attr_setschedparam(&attr, &sp);
        pthread_create(&thread, &attr, servo_main, 0);
        pthread_attr_destroy(&attr);
        servo_thread = thread; have_servo_thread = 1;
    }
}
void hdStopScheduler(void) {
    if (!running) return;
    running = 0;
    if (have_servo_thread) { pthread_join(thread, 0); have_servo_thread = 0; servo_tid = 0; }
    memset(force, 0, sizeof force);  /* the motors are off once the servo loop stops */
}

/* ---- test hooks ---- */
void fake_reset(int manual_mode) {
    running = 0; ncb = 0; ticks = frames = force_writes = frame_violations = thread_violations = 0;
    manual = manual_mode; inited = enabled = in_frame = clamping = ramping = 0; nerr = 0;
    init_error = 0; require_gtdd = 1; unplugged = session_lost = 0; inits = 0;
    unplug_file_says = -1;
    fail_at_tick = -1; max_force_seen = 0; nominal_max_force = 7.9; nominal_continuous = 1.75;
    temperature = 0.0; tau_s = 10.0; warm = 0;
    warm_events = exceeded_events = watchdog_trips = last_warm_tick = 0;
    calibration = OK; calibration_style = AUTO; inkwell = at_reset_pose = 0;
    cal_delay = 50; cal_pending = -1; enc_reset_running = updates = 0;
    last_update_style = 0; rate = 1000; buttons = 0;  /* the watchdog stays as set */
    memset(force, 0, sizeof force); memset(V, 0, sizeof V); memset(offset, 0, sizeof offset);
    memset(period_hist, 0, sizeof period_hist); memset(dur_hist, 0, sizeof dur_hist);
    nperiods = ndurs = 0; dur_max_us = period_max_us = 0.0;
    double I[16] = {1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1}; memcpy(T, I, sizeof T);
}
void fake_tick(int n) { for (int i = 0; i < n && running; i++) one_tick(); }
void fake_set_transform(const double *m) { memcpy(T, m, sizeof T); }
void fake_set_velocity(double x, double y, double z) { V[0] = x; V[1] = y; V[2] = z; }
void fake_set_buttons(int b) { buttons = b; }
/* state: OK, NEEDS_UPDATE or NEEDS_MANUAL_INPUT; not OK puts the uncalibrated offset on. */
void fake_set_calibration(unsigned int state, int styles) {
    calibration = state; calibration_style = styles; cal_pending = -1;
    if (state == OK) memset(offset, 0, sizeof offset); else set_uncalibrated_offset();
}
void fake_set_calibration_delay(long n) { cal_delay = n; }
void fake_set_inkwell(int in) { inkwell = in; }
void fake_set_at_reset_pose(int at) { at_reset_pose = at; }
void fake_set_nominal_max_force(double f) { nominal_max_force = f; }
void fake_set_nominal_continuous_force(double f) { nominal_continuous = f; }
void fake_set_thermal(double tau, double temp) { tau_s = tau; temperature = temp; }
void fake_set_watchdog_us(long us) { watchdog_ns = us * 1000L; }
void fake_require_gtdd_home(int on) { require_gtdd = on; }
/* The scheduler thread's policy * 1000 + its priority (SCHED_OTHER 0, SCHED_FIFO 1001..1099),
 * as the kernel has it (glibc's pthread_getschedparam would give the creation attributes it
 * cached, not a change the thread made with sched_setscheduler); -1 with no scheduler thread
 * (or before it ran). */
long fake_thread_policy(void) {
    struct sched_param sp;
    long tid = servo_tid;
    if (!have_servo_thread || tid == 0) return -1;
    int policy = sched_getscheduler((pid_t)tid);
    if (policy < 0 || sched_getparam((pid_t)tid, &sp) != 0) return -1;
    return (long)policy * 1000 + sp.sched_priority;
}
void fake_fail_init(unsigned int code) { init_error = code; }
void fake_unplug(void) { unplugged = 1; if (inited) session_lost = 1; }
void fake_replug(void) { unplugged = 0; }
void fake_fail_at_tick(long tick, unsigned int code) { fail_at_tick = tick; fail_code = code; }
double fake_force(int i) { return force[i]; }
double fake_max_force_seen(void) { return max_force_seen; }  /* squared magnitude, N^2 */
double fake_temperature(void) { return temperature; }
double fake_offset(int i) { return offset[i]; }
long fake_counter(int which) {
    switch (which) {
        case 0: return ticks; case 1: return frames; case 2: return force_writes;
        case 3: return frame_violations; case 4: return thread_violations;
        case 5: return (long)rate; case 6: return ncb ? cb_prio[0] : -1;
        case 7: return enabled * 100 + running * 10 + inited; case 8: return last_update_style;
        case 9: return calibration; case 10: return warm_events;
        case 11: return exceeded_events; case 12: return watchdog_trips;
        case 13: return enc_reset_running; case 14: return updates;
        case 15: return clamping * 10 + ramping; case 16: return warm;
        case 17: return inits;
        case 18: { long n = 0; for (int i = 0; i < ncb; i++) n += cbs[i] != 0; return n; }
    }
    return -1;
}
/* Percentile q (0..1) of the callbacks' periods (which 0) or durations (which 1), us. */
double fake_timing(int which, double q) {
    long *h = which ? dur_hist : period_hist;
    long n = which ? ndurs : nperiods;
    if (n == 0) return 0.0;
    if (q >= 1.0) return which ? dur_max_us : period_max_us;
    long want = (long)(q * (double)n), acc = 0;
    for (int i = 0; i < NBINS; i++) { acc += h[i]; if (acc > want) return i * 10.0 + 5.0; }
    return NBINS * 10.0;
}
long fake_timing_count(int which) { return which ? ndurs : nperiods; }
/* Callbacks whose duration exceeded us microseconds. */
long fake_timing_over(int which, double us) {
    long *h = which ? dur_hist : period_hist, n = 0;
    for (long i = (long)(us / 10.0); i < NBINS; i++) n += h[i];
    return n;
}
