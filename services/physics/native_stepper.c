/* A thread that runs mj_step on a world with no GIL in it (services/physics/stepper.py).
 *
 * The physics federate steps its world ahead while the other members of its group run their
 * events. A Python thread doing that needs the GIL twice a step (to start the step and to report
 * it done), and so waits for the busy main thread at every step. This thread is C from start to
 * end: Python starts it through ctypes, which releases the GIL for the whole call, and it never
 * touches a Python object. The main thread hands it a step with a semaphore post and takes the
 * step back with a semaphore wait, or a try-wait between its events; both order the memory, so
 * what the main thread wrote into mjData before the post is what the step reads, and what the
 * step wrote is what it reads after the wait. mj_step itself comes as a function pointer from the
 * libmujoco the bindings loaded, so nothing here is built against MuJoCo.
 */

#include <errno.h>
#include <semaphore.h>
#include <stdlib.h>

typedef void (*step_fn)(const void *model, void *data);

typedef struct {
    sem_t go;
    sem_t done;
    step_fn step;
    const void *model;
    void *data;
    int stop;
} stepper;

static void wait_for(sem_t *s) {
    while (sem_wait(s) != 0 && errno == EINTR) {
    }
}

stepper *cosim_stepper_new(step_fn step, const void *model, void *data) {
    stepper *s = calloc(1, sizeof *s);
    if (s == NULL) return NULL;
    if (sem_init(&s->go, 0, 0) != 0 || sem_init(&s->done, 0, 0) != 0) {
        free(s);
        return NULL;
    }
    s->step = step;
    s->model = model;
    s->data = data;
    return s;
}

/* The thread's body: one mj_step per go, until stopped. */
void cosim_stepper_serve(stepper *s) {
    for (;;) {
        wait_for(&s->go);
        if (__atomic_load_n(&s->stop, __ATOMIC_ACQUIRE)) return;
        s->step(s->model, s->data);
        sem_post(&s->done);
    }
}

void cosim_stepper_go(stepper *s) { sem_post(&s->go); }

void cosim_stepper_wait(stepper *s) { wait_for(&s->done); }

/* 1 if the step handed over has ended (and is taken back), 0 if it still runs: never blocks. */
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
    free(s);
}
