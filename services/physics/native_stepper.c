/* A thread that runs mj_step on a world with no GIL in it (services/physics/stepper.py).
 *
 * The physics federate steps its world ahead while the other members of its group run their
 * events. A Python thread doing that needs the GIL twice a step (to start the step and to report
 * it done), and so waits for the busy main thread at every step. This thread is C from start to
 * end: Python starts it through ctypes, which releases the GIL for the whole call, and it never
 * touches a Python object. The main thread hands it steps with a semaphore post and takes them
 * back with a semaphore wait, or a try-wait between its events; both order the memory, so what
 * the main thread wrote into mjData before the post is what the steps read, and what they wrote
 * is what it reads after the wait. mj_step itself comes as a function pointer from the libmujoco
 * the bindings loaded, so nothing here is built against MuJoCo.
 *
 * A handover may hold several steps, when nothing in Python has to run between them: before each
 * step after the first, the thread copies qpos and qvel for the observers of that step's start
 * and then applies the conveyor drive, as World.hold_observations and World.before_step would.
 * It counts the steps done under a mutex, so the main thread can wait for one of them (and its
 * copy) without waiting for the whole handover.
 *
 * An error MuJoCo raises inside mj_step (an arena too small, say) calls the error handler, which
 * must not return. The Python bindings give each of their calls a handler that raises; this
 * thread is not theirs, and without one MuJoCo prints and ends the process. So the library sets
 * MuJoCo's error handler (mju_user_error, whose address Python passes) to one that, in a step of
 * this thread, keeps the message and jumps back out of mj_step: the handover ends there, and the
 * main thread raises the message where it takes the steps back. Anywhere else it does what
 * MuJoCo does without a handler.
 */

#include <errno.h>
#include <pthread.h>
#include <semaphore.h>
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef void (*step_fn)(const void *model, void *data);
typedef void (*error_fn)(const char *msg);

typedef struct {
    sem_t go;
    sem_t done;
    step_fn step;
    const void *model;
    void *data;
    int stop;
    /* mjData's state arrays and their lengths */
    double *qpos, *qvel;
    long nq, nv;
    /* the current handover: its steps, the belt drive and where the copies go (row k-1 holds
       the state at the start of step k) */
    int steps;
    const long *belt;
    long n_belt;
    double belt_speed;
    double *held_qpos, *held_qvel;
    /* set when the current handover's steps are all done (read without a call by the caller) */
    int finished;
    /* steps of the current handover done so far */
    pthread_mutex_t lock;
    pthread_cond_t progress;
    int steps_done;
    /* MuJoCo's error in a step of the current handover (empty: none), which ended it */
    char error[1024];
} stepper;

/* The stepper whose step this thread runs (NULL outside one), and where its error jumps to. */
static __thread stepper *stepping;
static __thread jmp_buf step_failed;
/* What mju_user_error held before this library's handler, for errors outside its steps. */
static error_fn previous_error;

static void on_mujoco_error(const char *msg) {
    stepper *s = stepping;
    if (s == NULL) {
        if (previous_error != NULL) previous_error(msg);
        fprintf(stderr, "ERROR: %s\n", msg);
        exit(EXIT_FAILURE);
    }
    snprintf(s->error, sizeof s->error, "%s", msg);
    stepping = NULL;
    longjmp(step_failed, 1);
}

/* Make MuJoCo's error handler (the variable mju_user_error at `user_error`) this library's. */
void cosim_stepper_catch_errors(error_fn *user_error) {
    if (*user_error != on_mujoco_error) {
        previous_error = *user_error;
        *user_error = on_mujoco_error;
    }
}

/* MuJoCo's error in the last handover, "" if none. */
const char *cosim_stepper_error(stepper *s) { return s->error; }

static void wait_for(sem_t *s) {
    while (sem_wait(s) != 0) {
        if (errno != EINTR) abort(); /* an invalid semaphore: going on would race on mjData */
    }
}

stepper *cosim_stepper_new(step_fn step, const void *model, void *data, double *qpos, double *qvel,
                           long nq, long nv) {
    stepper *s = calloc(1, sizeof *s);
    if (s == NULL) return NULL;
    if (sem_init(&s->go, 0, 0) != 0) {
        free(s);
        return NULL;
    }
    if (sem_init(&s->done, 0, 0) != 0) {
        sem_destroy(&s->go);
        free(s);
        return NULL;
    }
    if (pthread_mutex_init(&s->lock, NULL) != 0) {
        sem_destroy(&s->go);
        sem_destroy(&s->done);
        free(s);
        return NULL;
    }
    if (pthread_cond_init(&s->progress, NULL) != 0) {
        pthread_mutex_destroy(&s->lock);
        sem_destroy(&s->go);
        sem_destroy(&s->done);
        free(s);
        return NULL;
    }
    s->step = step;
    s->model = model;
    s->data = data;
    s->qpos = qpos;
    s->qvel = qvel;
    s->nq = nq;
    s->nv = nv;
    return s;
}

/* The thread's body: the steps of each handover, until stopped. */
void cosim_stepper_serve(stepper *s) {
    for (;;) {
        wait_for(&s->go);
        if (__atomic_load_n(&s->stop, __ATOMIC_ACQUIRE)) return;
        if (setjmp(step_failed) == 0) {
            stepping = s;
            for (int k = 0; k < s->steps; k++) {
                if (k > 0) {
                    for (long i = 0; i < s->n_belt; i++) {
                        s->qvel[s->belt[i]] = s->belt_speed;
                        s->qvel[s->belt[i] + 1] = 0.0;
                    }
                }
                s->step(s->model, s->data);
                if (k + 1 < s->steps) {
                    memcpy(s->held_qpos + k * s->nq, s->qpos, sizeof(double) * s->nq);
                    memcpy(s->held_qvel + k * s->nv, s->qvel, sizeof(double) * s->nv);
                }
                pthread_mutex_lock(&s->lock);
                s->steps_done = k + 1;
                pthread_cond_broadcast(&s->progress);
                pthread_mutex_unlock(&s->lock);
            }
            stepping = NULL;
        } else {  /* a step failed (s->error): whoever waits for a step of it wakes to the error */
            pthread_mutex_lock(&s->lock);
            s->steps_done = s->steps;
            pthread_cond_broadcast(&s->progress);
            pthread_mutex_unlock(&s->lock);
        }
        __atomic_store_n(&s->finished, 1, __ATOMIC_RELEASE);
        sem_post(&s->done);
    }
}

/* Hand over `steps` steps; from the second on, the belt drive sets qvel[belt[i]] to belt_speed
 * and qvel[belt[i] + 1] to 0, and the state at each step's start is copied into the held rows. */
void cosim_stepper_go(stepper *s, int steps, const long *belt, long n_belt, double belt_speed,
                      double *held_qpos, double *held_qvel) {
    s->steps = steps;
    s->belt = belt;
    s->n_belt = n_belt;
    s->belt_speed = belt_speed;
    s->held_qpos = held_qpos;
    s->held_qvel = held_qvel;
    s->error[0] = '\0';
    pthread_mutex_lock(&s->lock);
    s->steps_done = 0;
    pthread_mutex_unlock(&s->lock);
    __atomic_store_n(&s->finished, 0, __ATOMIC_RELEASE);
    sem_post(&s->go);
}

/* Where the flag "the handover's steps are done" is: the caller reads it between its events
 * without a call; a done handover is then taken back with cosim_stepper_try_wait. */
int *cosim_stepper_finished_flag(stepper *s) { return &s->finished; }

/* Block until `steps` steps of the current handover are done (with their copies). */
void cosim_stepper_wait_steps(stepper *s, int steps) {
    pthread_mutex_lock(&s->lock);
    while (s->steps_done < steps) pthread_cond_wait(&s->progress, &s->lock);
    pthread_mutex_unlock(&s->lock);
}

void cosim_stepper_wait(stepper *s) { wait_for(&s->done); }

/* 1 if the steps handed over have ended (and are taken back), 0 if they still run: never blocks. */
int cosim_stepper_try_wait(stepper *s) {
    while (sem_trywait(&s->done) != 0) {
        if (errno != EINTR) return 0;
    }
    return 1;
}

void cosim_stepper_stop(stepper *s) {
    __atomic_store_n(&s->stop, 1, __ATOMIC_RELEASE);
    sem_post(&s->go);
}

void cosim_stepper_free(stepper *s) {
    sem_destroy(&s->go);
    sem_destroy(&s->done);
    pthread_mutex_destroy(&s->lock);
    pthread_cond_destroy(&s->progress);
    free(s);
}
