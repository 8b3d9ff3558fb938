/* A fake OpenHaptics HD library for the tests: the exported functions and signatures the
 * touchx backend uses (hdDefines.h / hdScheduler.h), a scheduler thread at the requested rate,
 * and fake_* hooks for the tests. Device state: a stylus pose (mm), velocity (mm/s), buttons,
 * calibration state, the device's nominal peak force (N) and injected errors. */
#include <pthread.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

typedef struct { unsigned int errorCode; int internalErrorCode; unsigned int hHD; } HDErrorInfo;
typedef unsigned int (*HDSchedulerCallback)(void *);

#define MAXCB 8
static HDSchedulerCallback cbs[MAXCB];
static void *cb_data[MAXCB];
static unsigned short cb_prio[MAXCB];
static int ncb;
static volatile int running, manual, inited, enabled, in_frame;
static pthread_t thread, servo_thread;
static int have_servo_thread;
static unsigned long rate = 1000;  /* OpenHaptics' default too */
static volatile long ticks, frames, force_writes, frame_violations, thread_violations;
static double T[16] = {1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1};  /* column-major, mm */
static double V[3];
static int buttons;
static double force[3], max_force_seen, nominal_max_force = 7.9;
static unsigned int calibration = 0x5000, last_update_style;
static int calibration_style = 1 << 1;  /* HD_CALIBRATION_AUTO */
static unsigned int err_queue[16]; static int err_internal[16]; static volatile int nerr;
static unsigned int init_error;
static long fail_at_tick = -1; static unsigned int fail_code;

static void push_error(unsigned int code, int internal) {
    if (nerr < 16) { err_queue[nerr] = code; err_internal[nerr] = internal; nerr++; }
}
static int in_servo(void) {
    return !have_servo_thread || pthread_equal(pthread_self(), servo_thread);
}

unsigned int hdInitDevice(const char *name) {
    if (init_error) { push_error(init_error, -3); return 0xFFFFFFFF; }
    inited = 1; return 1;
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
void hdEnable(unsigned int cap) { if (cap == 0x4000) enabled = 1; }
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
    if (what == 0x2052) memcpy(v, T, sizeof T);
    else if (what == 0x2051) memcpy(v, V, sizeof V);
    else if (what == 0x2603) *v = nominal_max_force;
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
    if (!in_frame || !in_servo()) { frame_violations++; return; }
    for (int i = 0; i < 3; i++) force[i] = v[i];
    double m = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    if (m > max_force_seen) max_force_seen = m;
    force_writes++;
}
unsigned int hdCheckCalibration(void) { return calibration; }
void hdUpdateCalibration(unsigned int style) {
    last_update_style = style;
    if (calibration == 0x5001 && (style & calibration_style)) calibration = 0x5000;
}
void hdSetSchedulerRate(unsigned long r) { rate = r; }
unsigned long hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, unsigned short prio) {
    if (ncb >= MAXCB) { push_error(0x0501, 0); return 0; }
    cbs[ncb] = cb; cb_data[ncb] = data; cb_prio[ncb] = prio; return (unsigned long)(++ncb);
}
void hdUnschedule(unsigned long h) { if (h >= 1 && h <= (unsigned long)ncb) cbs[h - 1] = 0; }

static void one_tick(void) {
    if (fail_at_tick >= 0 && ticks == fail_at_tick) push_error(fail_code, 7);
    for (int i = 0; i < ncb; i++)
        if (cbs[i] && cbs[i](cb_data[i]) == 0) cbs[i] = 0;  /* HD_CALLBACK_DONE */
    ticks++;
}
static void *servo_main(void *arg) {
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
        pthread_create(&thread, 0, servo_main, 0);
        servo_thread = thread; have_servo_thread = 1;
    }
}
void hdStopScheduler(void) {
    if (!running) return;
    running = 0;
    if (have_servo_thread) { pthread_join(thread, 0); have_servo_thread = 0; }
}

/* ---- test hooks ---- */
void fake_reset(int manual_mode) {
    running = 0; ncb = 0; ticks = frames = force_writes = frame_violations = thread_violations = 0;
    manual = manual_mode; inited = enabled = in_frame = 0; nerr = 0; init_error = 0;
    fail_at_tick = -1; max_force_seen = 0; nominal_max_force = 7.9; calibration = 0x5000;
    calibration_style = 1 << 1; last_update_style = 0; rate = 1000; buttons = 0;
    memset(force, 0, sizeof force); memset(V, 0, sizeof V);
    double I[16] = {1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1}; memcpy(T, I, sizeof T);
}
void fake_tick(int n) { for (int i = 0; i < n && running; i++) one_tick(); }
void fake_set_transform(const double *m) { memcpy(T, m, sizeof T); }
void fake_set_velocity(double x, double y, double z) { V[0] = x; V[1] = y; V[2] = z; }
void fake_set_buttons(int b) { buttons = b; }
void fake_set_calibration(unsigned int state, int styles) {
    calibration = state; calibration_style = styles;
}
void fake_set_nominal_max_force(double f) { nominal_max_force = f; }
void fake_fail_init(unsigned int code) { init_error = code; }
void fake_fail_at_tick(long tick, unsigned int code) { fail_at_tick = tick; fail_code = code; }
double fake_force(int i) { return force[i]; }
double fake_max_force_seen(void) { return max_force_seen; }  /* squared magnitude, N^2 */
long fake_counter(int which) {
    switch (which) {
        case 0: return ticks; case 1: return frames; case 2: return force_writes;
        case 3: return frame_violations; case 4: return thread_violations;
        case 5: return (long)rate; case 6: return ncb ? cb_prio[0] : -1;
        case 7: return enabled * 100 + running * 10 + inited; case 8: return last_update_style;
        case 9: return calibration;
    }
    return -1;
}
