/*
 * hd_sim.c -- a simulated libHD (OpenHaptics' HD API) for haptic_collab's tests.
 *
 * Written for this project from the public HD API function signatures and constant values
 * (the OpenHaptics programmer's reference); no vendor header or code is copied. The tests build
 * it at test time:
 *
 *     cc -shared -fPIC -Wl,-soname,libHD.so -o DIR/libHD.so hd_sim.c -lpthread
 *
 * and the real pyOpenHaptics binding finds it through LD_LIBRARY_PATH=DIR (it loads "libHD.so").
 *
 * What it simulates: one device (handle 1) with a position, velocity and buttons the test sets;
 * nominal limits, model and workspace; a 1 kHz scheduler thread that calls the scheduled
 * callbacks; frames (hdBeginFrame/hdEndFrame) that commit the commanded force; an error FIFO
 * (hdGetError); the driver's safety errors (HD_EXCEEDED_MAX_FORCE when |F| exceeds the nominal
 * maximum, HD_EXCEEDED_MAX_VELOCITY when the stylus moves faster than the software velocity limit
 * while a force is commanded); an unplugged device (HD_COMM_ERROR in every frame, hdInitDevice
 * fails); a scheduler that stops calling back ("frozen").
 * It also counts violations of the HD threading rules: a frame begun or ended outside the
 * scheduler thread, nested or unbalanced frames, device state read or written outside a frame.
 *
 * What it does not simulate: kinematics and motors, the real scheduler's timing and priorities,
 * several devices, calibration, the real driver's exact error semantics.
 *
 * The sim_* functions are test hooks, not part of the HD API. A process that cannot call them
 * (``haptic client`` run as a command) uses two environment variables instead:
 * HD_SIM_POSITION="x,y,z" sets the stylus position [mm, device frame] (read by hdInitDevice);
 * HD_SIM_REPORT=FILE makes hdDisableDevice write one JSON line to FILE: the frames run, the
 * violations counted, the largest force the motors displayed [N, device frame] and the force
 * the last frame displayed.
 */
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef unsigned int HHD;
typedef unsigned int HDenum;
typedef unsigned int HDerror;
typedef unsigned int HDCallbackCode;
typedef unsigned long HDSchedulerHandle;
typedef unsigned short HDushort;
typedef unsigned char HDboolean;
typedef const char *HDstring;
typedef HDCallbackCode (*HDSchedulerCallback)(void *);
typedef struct {
    HDerror errorCode;
    int internalErrorCode;
    HHD hHD;
} HDErrorInfo;

#define HANDLE 1u
#define INVALID_HANDLE 0xFFFFFFFFu
#define CALLBACK_DONE 0u

enum {
    P_BUTTONS = 0x2000,
    P_POSITION = 0x2050,
    P_VELOCITY = 0x2051,
    P_TRANSFORM = 0x2052,
    P_MODEL = 0x2501,
    P_VENDOR = 0x2503,
    P_SERIAL = 0x2504,
    P_MAX_WORKSPACE = 0x2550,
    P_USABLE_WORKSPACE = 0x2551,
    P_UPDATE_RATE = 0x2600,
    P_MAX_STIFFNESS = 0x2602,
    P_MAX_FORCE = 0x2603,
    P_MAX_CONTINUOUS_FORCE = 0x2604,
    P_SOFTWARE_VELOCITY_LIMIT = 0x2606,
    P_MAX_DAMPING = 0x2609,
    P_FORCE = 0x2700,
    P_FORCE_OUTPUT = 0x4000,
};

enum {
    E_INVALID_ENUM = 0x0100,
    E_INVALID_OPERATION = 0x0103,
    E_BAD_HANDLE = 0x0104,
    E_EXCEEDED_MAX_FORCE = 0x0201,
    E_EXCEEDED_MAX_VELOCITY = 0x0203,
    E_ALREADY_INITIATED = 0x0301,
    E_COMM_ERROR = 0x0302,
    E_COMM_CONFIG_ERROR = 0x0303,
    E_ILLEGAL_BEGIN = 0x0400,
    E_ILLEGAL_END = 0x0401,
    E_SCHEDULER_FULL = 0x0501,
};

static pthread_mutex_t mu = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t cv = PTHREAD_COND_INITIALIZER;

/* the device */
static char model[64] = "Touch";
static char vendor[64] = "3D Systems (simulated)";
static char device_name[64] = "Default Device";
static double max_force = 3.3, max_continuous = 0.88, max_stiffness = 0.4 /* N/mm */,
              max_damping = 0.004 /* N/(mm/s) */, velocity_limit = 800.0 /* mm/s */;
static double usable_ws[6] = {-80, -60, -35, 80, 60, 35}; /* mm: min xyz, max xyz */
static double max_ws[6] = {-110, -90, -60, 110, 110, 60};
static int initialized, force_output, unplugged, frozen;
static double pos[3], vel[3], force_cmd[3], force_out[3], peak_out[3], last_frame_out[3];
static int buttons;
static HDerror injected;

/* errors */
#define NERR 32
static HDErrorInfo errs[NERR];
static int nerr;

/* frames and scheduler */
static int in_frame, running;
static pthread_t sched_thread;
static unsigned long ticks, frames, violations;
#define MAXCB 16
static struct {
    HDSchedulerCallback cb;
    void *data;
    int active, sync, done;
} cbs[MAXCB];

static void push_error(HDerror code, int internal) /* mu held */
{
    if (nerr < NERR) {
        errs[nerr].errorCode = code;
        errs[nerr].internalErrorCode = internal;
        errs[nerr].hHD = HANDLE;
        nerr++;
    }
}

static int on_scheduler_thread(void) /* mu held */
{
    return running && pthread_equal(pthread_self(), sched_thread);
}

static double norm2(const double *v) { return v[0] * v[0] + v[1] * v[1] + v[2] * v[2]; }

/* -- device -- */

static void position_from_environment(void) /* mu held */
{
    const char *s = getenv("HD_SIM_POSITION");
    char *end;
    for (int i = 0; s && i < 3; i++) {
        pos[i] = strtod(s, &end);
        s = *end == ',' ? end + 1 : 0;
    }
}

HHD hdInitDevice(HDstring name)
{
    HHD h = INVALID_HANDLE;
    pthread_mutex_lock(&mu);
    position_from_environment();
    if (unplugged)
        push_error(E_COMM_ERROR, 1);
    else if (name && strcmp(name, "Default Device") && strcmp(name, device_name))
        push_error(E_COMM_CONFIG_ERROR, 2);
    else if (initialized)
        push_error(E_ALREADY_INITIATED, 0);
    else {
        initialized = 1;
        force_output = 0;
        memset(force_cmd, 0, sizeof force_cmd);
        memset(force_out, 0, sizeof force_out);
        h = HANDLE;
    }
    pthread_mutex_unlock(&mu);
    return h;
}

static void write_report(void) /* mu held */
{
    const char *path = getenv("HD_SIM_REPORT");
    FILE *f = path ? fopen(path, "a") : 0;
    if (!f)
        return;
    fprintf(f,
            "{\"frames\": %lu, \"violations\": %lu, \"peak_force\": [%.17g, %.17g, %.17g], "
            "\"last_frame_force\": [%.17g, %.17g, %.17g]}\n",
            frames, violations, peak_out[0], peak_out[1], peak_out[2], last_frame_out[0],
            last_frame_out[1], last_frame_out[2]);
    fclose(f);
}

void hdDisableDevice(HHD h)
{
    pthread_mutex_lock(&mu);
    if (h != HANDLE || !initialized)
        push_error(E_BAD_HANDLE, 0);
    write_report();
    initialized = 0;
    force_output = 0;
    memset(force_out, 0, sizeof force_out);
    pthread_mutex_unlock(&mu);
}

HHD hdGetCurrentDevice(void) { return initialized ? HANDLE : INVALID_HANDLE; }
void hdMakeCurrentDevice(HHD h) { (void)h; }

void hdEnable(HDenum cap)
{
    pthread_mutex_lock(&mu);
    if (cap == P_FORCE_OUTPUT)
        force_output = 1;
    pthread_mutex_unlock(&mu);
}

void hdDisable(HDenum cap)
{
    pthread_mutex_lock(&mu);
    if (cap == P_FORCE_OUTPUT) {
        force_output = 0;
        memset(force_out, 0, sizeof force_out);
    }
    pthread_mutex_unlock(&mu);
}

HDboolean hdIsEnabled(HDenum cap) { return cap == P_FORCE_OUTPUT ? (HDboolean)force_output : 0; }

HDErrorInfo hdGetError(void)
{
    HDErrorInfo e = {0, 0, 0};
    pthread_mutex_lock(&mu);
    if (nerr) {
        e = errs[0];
        memmove(errs, errs + 1, (size_t)(nerr - 1) * sizeof *errs);
        nerr--;
    }
    pthread_mutex_unlock(&mu);
    return e;
}

HDstring hdGetErrorString(HDerror code) { return code ? "simulated HD error" : "no error"; }

HDstring hdGetString(HDenum p)
{
    switch (p) {
    case P_MODEL: return model;
    case P_VENDOR: return vendor;
    case P_SERIAL: return "SIM-0001";
    default:
        pthread_mutex_lock(&mu);
        push_error(E_INVALID_ENUM, 0);
        pthread_mutex_unlock(&mu);
        return "";
    }
}

/* -- frames and state -- */

void hdBeginFrame(HHD h)
{
    pthread_mutex_lock(&mu);
    if (!on_scheduler_thread())
        violations++;
    if (h != HANDLE || !initialized)
        push_error(E_BAD_HANDLE, 0);
    if (in_frame) {
        push_error(E_ILLEGAL_BEGIN, 0);
        violations++;
    }
    in_frame = 1;
    memset(force_cmd, 0, sizeof force_cmd); /* a frame that sets no force commands none */
    if (unplugged)
        push_error(E_COMM_ERROR, 3);
    pthread_mutex_unlock(&mu);
}

void hdEndFrame(HHD h)
{
    pthread_mutex_lock(&mu);
    if (!on_scheduler_thread())
        violations++;
    if (h != HANDLE)
        push_error(E_BAD_HANDLE, 0);
    if (!in_frame) {
        push_error(E_ILLEGAL_END, 0);
        violations++;
    }
    in_frame = 0;
    frames++;
    double f2 = norm2(force_cmd);
    if (unplugged || !force_output || !initialized) {
        memset(force_out, 0, sizeof force_out);
    } else if (injected) {
        push_error(injected, 4);
        injected = 0;
        memset(force_out, 0, sizeof force_out);
    } else if (f2 > max_force * max_force) {
        push_error(E_EXCEEDED_MAX_FORCE, 5);
        memset(force_out, 0, sizeof force_out);
    } else if (f2 > 0.0 && norm2(vel) > velocity_limit * velocity_limit) {
        push_error(E_EXCEEDED_MAX_VELOCITY, 6);
        memset(force_out, 0, sizeof force_out);
    } else {
        memcpy(force_out, force_cmd, sizeof force_out);
        if (f2 > norm2(peak_out))
            memcpy(peak_out, force_out, sizeof peak_out);
    }
    memcpy(last_frame_out, force_out, sizeof last_frame_out);
    pthread_mutex_unlock(&mu);
}

static void state_access(void) /* mu held: device state belongs to a frame on the scheduler */
{
    if (!in_frame || !on_scheduler_thread())
        violations++;
}

void hdGetIntegerv(HDenum p, int *v)
{
    pthread_mutex_lock(&mu);
    if (p == P_BUTTONS) {
        state_access();
        *v = buttons;
    } else if (p == P_UPDATE_RATE) {
        *v = 1000;
    } else {
        push_error(E_INVALID_ENUM, 0);
    }
    pthread_mutex_unlock(&mu);
}

void hdGetDoublev(HDenum p, double *v)
{
    pthread_mutex_lock(&mu);
    switch (p) {
    case P_POSITION: state_access(); memcpy(v, pos, sizeof pos); break;
    case P_VELOCITY: state_access(); memcpy(v, vel, sizeof vel); break;
    case P_TRANSFORM:
        state_access();
        memset(v, 0, 16 * sizeof *v);
        v[0] = v[5] = v[10] = v[15] = 1.0;
        v[12] = pos[0], v[13] = pos[1], v[14] = pos[2];
        break;
    case P_FORCE: memcpy(v, force_cmd, sizeof force_cmd); break;
    case P_MAX_FORCE: *v = max_force; break;
    case P_MAX_CONTINUOUS_FORCE: *v = max_continuous; break;
    case P_MAX_STIFFNESS: *v = max_stiffness; break;
    case P_MAX_DAMPING: *v = max_damping; break;
    case P_SOFTWARE_VELOCITY_LIMIT: *v = velocity_limit; break;
    case P_USABLE_WORKSPACE: memcpy(v, usable_ws, sizeof usable_ws); break;
    case P_MAX_WORKSPACE: memcpy(v, max_ws, sizeof max_ws); break;
    default: push_error(E_INVALID_ENUM, 0);
    }
    pthread_mutex_unlock(&mu);
}

void hdSetDoublev(HDenum p, const double *v)
{
    pthread_mutex_lock(&mu);
    if (p == P_FORCE) {
        if (!in_frame || !on_scheduler_thread()) {
            violations++;
            push_error(E_INVALID_OPERATION, 0);
        } else {
            memcpy(force_cmd, v, sizeof force_cmd);
        }
    } else {
        push_error(E_INVALID_ENUM, 0);
    }
    pthread_mutex_unlock(&mu);
}

/* -- scheduler -- */

static void *scheduler_loop(void *arg)
{
    (void)arg;
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    pthread_mutex_lock(&mu);
    while (running) {
        pthread_mutex_unlock(&mu);
        t.tv_nsec += 1000000;
        if (t.tv_nsec >= 1000000000) {
            t.tv_nsec -= 1000000000;
            t.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &t, 0);
        pthread_mutex_lock(&mu);
        if (!running)
            break;
        if (!frozen) {
            for (int i = 0; i < MAXCB; i++) {
                if (!cbs[i].active)
                    continue;
                HDSchedulerCallback cb = cbs[i].cb;
                void *data = cbs[i].data;
                pthread_mutex_unlock(&mu);
                HDCallbackCode r = cb(data);
                pthread_mutex_lock(&mu);
                if (cbs[i].active && (r == CALLBACK_DONE || cbs[i].sync)) {
                    cbs[i].active = 0;
                    cbs[i].done = 1;
                    pthread_cond_broadcast(&cv);
                }
            }
        }
        ticks++;
    }
    pthread_mutex_unlock(&mu);
    return 0;
}

void hdStartScheduler(void)
{
    pthread_mutex_lock(&mu);
    if (!running) {
        running = 1;
        pthread_create(&sched_thread, 0, scheduler_loop, 0); /* it waits for mu: id is set */
    }
    pthread_mutex_unlock(&mu);
}

void hdStopScheduler(void)
{
    pthread_mutex_lock(&mu);
    if (!running || pthread_equal(pthread_self(), sched_thread)) {
        if (running)
            push_error(E_INVALID_OPERATION, 0);
        pthread_mutex_unlock(&mu);
        return;
    }
    running = 0;
    pthread_t th = sched_thread;
    pthread_mutex_unlock(&mu);
    pthread_join(th, 0);
    pthread_mutex_lock(&mu);
    for (int i = 0; i < MAXCB; i++) /* wake synchronous callers; asynchronous ones stay */
        if (cbs[i].active && cbs[i].sync) {
            cbs[i].active = 0;
            cbs[i].done = 1;
        }
    pthread_cond_broadcast(&cv);
    pthread_mutex_unlock(&mu);
}

void hdSetSchedulerRate(unsigned long hz) { (void)hz; }
double hdGetSchedulerTimeStamp(void) { return 0.001; }

static long add_callback(HDSchedulerCallback cb, void *data, int sync) /* mu held */
{
    for (int i = 0; i < MAXCB; i++) {
        if (!cbs[i].active) {
            cbs[i].cb = cb;
            cbs[i].data = data;
            cbs[i].active = 1;
            cbs[i].sync = sync;
            cbs[i].done = 0;
            return i;
        }
    }
    push_error(E_SCHEDULER_FULL, 0);
    return -1;
}

HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, HDushort priority)
{
    (void)priority;
    pthread_mutex_lock(&mu);
    long i = add_callback(cb, data, 0);
    pthread_mutex_unlock(&mu);
    return (HDSchedulerHandle)i;
}

void hdScheduleSynchronous(HDSchedulerCallback cb, void *data, HDushort priority)
{
    (void)priority;
    pthread_mutex_lock(&mu);
    if (!running) {
        pthread_mutex_unlock(&mu);
        cb(data);
        return;
    }
    long i = add_callback(cb, data, 1);
    while (i >= 0 && !cbs[i].done && running)
        pthread_cond_wait(&cv, &mu);
    pthread_mutex_unlock(&mu);
}

void hdUnschedule(HDSchedulerHandle h)
{
    pthread_mutex_lock(&mu);
    if (h < MAXCB) {
        cbs[h].active = 0;
        cbs[h].done = 1;
    }
    pthread_mutex_unlock(&mu);
}

HDboolean hdWaitForCompletion(HDSchedulerHandle h, unsigned int how)
{
    (void)how;
    return h < MAXCB && cbs[h].active;
}

/* -- test hooks (not part of the HD API) -- */

void sim_set_position(double x, double y, double z)
{
    pthread_mutex_lock(&mu);
    pos[0] = x, pos[1] = y, pos[2] = z;
    pthread_mutex_unlock(&mu);
}

void sim_set_velocity(double x, double y, double z)
{
    pthread_mutex_lock(&mu);
    vel[0] = x, vel[1] = y, vel[2] = z;
    pthread_mutex_unlock(&mu);
}

void sim_set_buttons(int b) { buttons = b; }

void sim_get_force(double *f) /* the force the motors display now [N], device frame */
{
    pthread_mutex_lock(&mu);
    memcpy(f, force_out, sizeof force_out);
    pthread_mutex_unlock(&mu);
}

void sim_set_model(const char *m) { strncpy(model, m, sizeof model - 1); }
void sim_set_device_name(const char *n) { strncpy(device_name, n, sizeof device_name - 1); }

void sim_set_limits(double force, double continuous, double stiffness, double damping,
                    double velocity)
{
    max_force = force, max_continuous = continuous, max_stiffness = stiffness;
    max_damping = damping, velocity_limit = velocity;
}

void sim_set_usable_workspace(const double *w) { memcpy(usable_ws, w, sizeof usable_ws); }
void sim_inject_error(unsigned int code) { injected = code; } /* at the next frame's end */
void sim_unplug(int on) { unplugged = on; }
void sim_freeze(int on) { frozen = on; }
unsigned long sim_ticks(void) { return ticks; }
unsigned long sim_frames(void) { return frames; }
unsigned long sim_violations(void) { return violations; }
int sim_scheduler_running(void) { return running; }
int sim_initialized(void) { return initialized; }
int sim_force_output(void) { return force_output; }
int sim_pending_errors(void) { return nerr; }

int sim_callbacks_active(void)
{
    int n = 0;
    pthread_mutex_lock(&mu);
    for (int i = 0; i < MAXCB; i++)
        n += cbs[i].active;
    pthread_mutex_unlock(&mu);
    return n;
}
